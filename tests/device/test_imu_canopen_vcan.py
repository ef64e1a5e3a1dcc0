"""The IMU as a CANopen device on a real SocketCAN bus: push, pull, faults, and the whole loop.

The emulated IMU runs in its own process (``python -m canical emulate``), as a sensor
would be its own box; the tools talk to it over vcan with real CANopen SDO. Every fault
must end the tool with one line and a non-zero exit, and leave the device running the
set it ran before: the interrupted-download test counts partial activations over many
kills at random moments, and there must be none.
"""

from __future__ import annotations

import contextlib
import random
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

from canical.device.can_network import network_on, sdo_client_filters
from canical.device.sdo_download import ImuClient, push_sets
from canical.errors import CanicalError
from canical.frames.imu_dictionary import AXES, imu_objects, pack_active
from canical.sets import coefficient_file
from canical.sets.coefficient_file import set_crc

try:
    from support.imu_fixtures import SERIAL, imu_set, imu_sets
except ImportError:  # pragma: no cover
    from tests.imu_fixtures import SERIAL, imu_set, imu_sets  # type: ignore[no-redef]

NODE = 0x22
READY_TIMEOUT_S = 90.0  # interpreter start and imports are slow inside the UML guest
TIMEOUT = "1.0"


class Device:
    """An emulated IMU process; ``start`` again after ``kill`` is a power cycle."""

    def __init__(self, channel: str, state: Path, *extra: str, node: int = NODE) -> None:
        self.channel, self.state, self.extra, self.node = channel, state, extra, node
        self.proc: subprocess.Popen[str] | None = None

    def start(self) -> Device:
        cmd = [sys.executable, "-m", "canical", "emulate", "--interface", "socketcan", "--channel",
               self.channel, "--node", hex(self.node), "--serial", str(SERIAL), "--state", str(self.state),
               *self.extra]
        self.log = self.state.with_suffix(".log")
        with self.log.open("a") as err:
            self.proc = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=err, text=True)
        line = _readline(self.proc, READY_TIMEOUT_S)
        assert line.startswith("ready"), f"emulator did not start: {line!r}: {self.log.read_text()[-2000:]}"
        return self

    def kill(self) -> None:
        if self.proc and self.proc.poll() is None:
            self.proc.kill()
            self.proc.wait(10)

    def stop(self) -> None:
        if self.proc and self.proc.poll() is None:
            self.proc.terminate()
            try:
                self.proc.wait(10)
            except subprocess.TimeoutExpired:
                self.kill()


def _readline(proc: subprocess.Popen[str], timeout: float) -> str:
    out: list[str] = []
    reader = threading.Thread(target=lambda: out.append(proc.stdout.readline()), daemon=True)  # type: ignore[union-attr]
    reader.start()
    reader.join(timeout)
    return out[0] if out else ""


@contextlib.contextmanager
def device(channel: str, tmp_path: Path, *extra: str, name: str = "imu.json") -> Iterator[Device]:
    d = Device(channel, tmp_path / name, *extra).start()
    try:
        yield d
    finally:
        d.stop()


@contextlib.contextmanager
def client(channel: str, timeout: float = 1.0, node: int = NODE) -> Iterator[ImuClient]:
    with network_on("socketcan", channel, can_filters=sdo_client_filters(node)) as network:
        yield ImuClient(network, node, timeout)


def canical(*args: str, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "canical", *args], capture_output=True, text=True,
                          timeout=timeout, check=False)


def bus_args(channel: str) -> list[str]:
    return ["--node", hex(NODE), "--channel", channel, "--timeout", TIMEOUT]


def write_sets(folder: Path, family: int = 0, sensor: str | None = None) -> list[str]:
    folder.mkdir(parents=True, exist_ok=True)
    paths = []
    for axis, cset in (imu_sets(family) if sensor is None else imu_sets(family, sensor)).items():
        path = folder / f"imu-{axis}.yaml"
        coefficient_file.save(path, cset)
        paths.append(str(path))
    return paths


def ids(family: int) -> dict[str, int]:
    return {a: set_crc(imu_set(a, family)) for a in AXES}


def assert_one_line_error(proc: subprocess.CompletedProcess[str], *needles: str) -> None:
    assert proc.returncode == 2, proc.stdout + proc.stderr
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and "Traceback" not in proc.stderr, proc.stderr
    for needle in needles:
        assert needle in lines[0], lines[0]


# --------------------------------------------------------------------------------------------


@pytest.mark.vcan
def test_push_pull_round_trip_survives_power_cycle(vcan_channel: str, tmp_path: Path) -> None:
    paths = write_sets(tmp_path / "sets")
    with device(vcan_channel, tmp_path, "--rate", "50") as dev:
        dry = canical("push", *paths, *bus_args(vcan_channel), "--dry-run")
        assert dry.returncode == 0, dry.stderr
        assert "nothing written" in dry.stdout and "-> bank A" in dry.stdout
        with client(vcan_channel) as c:
            assert c.status().activations == 0
        pushed = canical("push", *paths, *bus_args(vcan_channel))
        assert pushed.returncode == 0, pushed.stderr
        assert "stored for power-up" in pushed.stdout
        dev.kill()  # power cut: what was stored must come back
        dev.start()
        pulled = canical("pull", *bus_args(vcan_channel), "-o", str(tmp_path / "pulled-{axis}.yaml"))
        assert pulled.returncode == 0, pulled.stderr
        for axis in AXES:
            assert set_crc(coefficient_file.load(tmp_path / f"pulled-{axis}.yaml")) == ids(0)[axis]
        again = canical("push", *write_sets(tmp_path / "sets1", family=1), *bus_args(vcan_channel))
        assert again.returncode == 0, again.stderr
        with client(vcan_channel) as c:
            status = c.status()
        assert status.active_ids == ids(1) and set(status.active.values()) == {"B"}


@pytest.mark.vcan
def test_spline_sets_go_over_sdo_and_run_on_the_device_in_c(vcan_channel: str, tmp_path: Path) -> None:
    """Sets with spline terms (a piecewise cubic of temperature, bias and scale form): pushed,
    read back, stored and pulled byte for byte; the correcting device runs them in the firmware's
    C evaluator; a set too long for the device's banks is refused in one line, nothing written."""
    from dataclasses import replace

    from support.firmware_cases import ALL_TERMS

    from canical.sets.terms import term_from_dict

    names = ("channel-spline", "channel-spline-scale")
    splines = tuple(term_from_dict(ALL_TERMS[k]) for k in names)
    folder = tmp_path / "splines"
    folder.mkdir()
    paths, pushed_ids = [], {}
    for axis, cset in imu_sets().items():
        with_spline = coefficient_file.loads(coefficient_file.dumps(replace(cset, terms=splines)))
        paths.append(str(folder / f"imu-{axis}.yaml"))
        coefficient_file.save(paths[-1], with_spline)
        pushed_ids[axis] = set_crc(with_spline)
    big = folder / "big.yaml"
    rng = random.Random(3)
    wide = [replace(splines[0], params=replace(
                splines[0].params, knots=tuple(sorted(rng.uniform(0.0, 50.0) for _ in range(64))),
                pieces=tuple(tuple(rng.gauss(0.0, 1e-3) for _ in range(4)) for _ in range(63))))
            for _ in range(4)]
    coefficient_file.save(big, replace(imu_set("z"), terms=tuple(wide)))
    with device(vcan_channel, tmp_path, "--rate", "50", "--correct") as dev:
        assert_one_line_error(canical("push", str(big), *bus_args(vcan_channel)),
                              "not for this device", "the device's coefficient banks hold 16384")
        pushed = canical("push", *paths, *bus_args(vcan_channel))
        assert pushed.returncode == 0, pushed.stderr
        pulled = canical("pull", *bus_args(vcan_channel), "-o", str(tmp_path / "pulled-{axis}.yaml"))
        assert pulled.returncode == 0, pulled.stderr
        for axis in AXES:
            back = coefficient_file.load(tmp_path / f"pulled-{axis}.yaml")
            assert set_crc(back) == pushed_ids[axis] and back.terms[0].params.knots == splines[0].params.knots
        with client(vcan_channel) as c:
            status = c.status()
        assert status.active_ids == pushed_ids and status.activations == 1  # the big set wrote nothing
        deadline = time.monotonic() + 30.0
        while dev.log.read_text().count("corrected on the device with the firmware evaluator (C)") < 3:
            assert time.monotonic() < deadline, dev.log.read_text()[-2000:]
            time.sleep(0.2)
    assert "correcting in Python" not in dev.log.read_text()


@pytest.mark.vcan
def test_the_tool_refuses_what_it_can_before_writing(vcan_channel: str, tmp_path: Path) -> None:
    good = write_sets(tmp_path / "good")
    foreign = write_sets(tmp_path / "foreign", sensor="4712")
    damaged = tmp_path / "damaged.yaml"
    damaged.write_text(Path(good[2]).read_text().replace("v0: ", "v0: 1", 1))
    absent = canical("push", good[2], "--node", "0x33", "--channel", vcan_channel, "--timeout", "0.3")
    assert_one_line_error(absent, "node 0x33", "no answer while reading its identity")
    with device(vcan_channel, tmp_path, "--rate", "0", "--rated-range", "70"):
        assert_one_line_error(canical("push", foreign[2], *bus_args(vcan_channel)),
                              "not for this device", "set is for sensor 4712, this device is serial 4711")
        assert_one_line_error(canical("push", good[2], *bus_args(vcan_channel)),
                              "does not cover the rated range ±70")
        assert_one_line_error(canical("push", str(damaged), *bus_args(vcan_channel)), "CRC mismatch")
        with client(vcan_channel) as c:
            assert c.status().activations == 0 and c.bank("z", "A")[2] == 0  # nothing written


@pytest.mark.vcan
def test_the_device_refuses_bad_banks_with_abort_codes(vcan_channel: str, tmp_path: Path) -> None:
    """Bypassing the tool (anyone on the bus can write): the device itself says no."""
    from canical.device.bank_payload import encode_set

    o = imu_objects()
    with device(vcan_channel, tmp_path, "--rate", "0"):
        with client(vcan_channel) as c:
            assert push_sets(c, {"z": ("z", imu_set("z"))}).status.active["z"] == "A"
            before = c.status()
            a, b = o.bank("z", "A"), o.bank("z", "B")
            with pytest.raises(CanicalError, match=r"0x08000022.*bank Z A is active"):
                c.download((a.index, a.content), b"{}", "overwriting the active bank")
            content, crc = encode_set(imu_set("z", family=1))
            c.download((b.index, b.content), content, "downloading")
            c.write_uint((b.index, b.crc), crc ^ 0x10, 4, "writing a wrong CRC")
            with pytest.raises(CanicalError, match=r"0x08000020.*CRC mismatch"):
                c.write_uint(o.active_banks, pack_active({"z": "B"}), 1, "activating")
            foreign, fcrc = encode_set(imu_set("z", sensor="4712"))
            c.download((b.index, b.content), foreign, "downloading")
            c.write_uint((b.index, b.crc), fcrc, 4, "writing the CRC")
            with pytest.raises(CanicalError, match=r"0x08000020.*serial 4711"):
                c.write_uint(o.active_banks, pack_active({"z": "B"}), 1, "activating")
            with pytest.raises(CanicalError, match=r"0x06090030"):
                c.write_uint(o.active_banks, 0xFF, 1, "activating")
            with pytest.raises(CanicalError, match=r"0x08000020"):
                c.write_uint(o.store, 0x12345678, 4, "storing without the signature")
            after = c.status()
        assert after.active == before.active and after.active_ids == before.active_ids
        assert after.activations == before.activations


@pytest.mark.vcan
def test_device_vanishing_mid_download_one_line_and_previous_set(vcan_channel: str, tmp_path: Path) -> None:
    with device(vcan_channel, tmp_path, "--rate", "50") as dev:
        proc = _second_push_mid_download(vcan_channel, tmp_path)
        dev.kill()
        out, err = proc.communicate(timeout=60)
        assert_one_line_error(subprocess.CompletedProcess(proc.args, proc.returncode, out, err),
                              "no answer while")
        dev.start()
        with client(vcan_channel) as c:
            assert c.status().active_ids == ids(0)


def _second_push_mid_download(channel: str, tmp_path: Path) -> subprocess.Popen[str]:
    """Push family 0, then start pushing family 1 and return once it is mid-bank."""
    old, new = write_sets(tmp_path / "old"), write_sets(tmp_path / "new", family=1)
    assert canical("push", *old, *bus_args(channel)).returncode == 0
    proc = subprocess.Popen([sys.executable, "-m", "canical", "push", *new, *bus_args(channel)],
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    _wait_for_download(channel)
    return proc


def _wait_for_download(channel: str, timeout: float = 30.0) -> None:
    """Return once segmented SDO download traffic to the node is seen (the push is mid-bank)."""
    import can

    with can.Bus(interface="socketcan", channel=channel,
                 can_filters=[{"can_id": 0x600 + NODE, "can_mask": 0x7FF}]) as bus:
        end = time.monotonic() + timeout
        segments = 0
        while time.monotonic() < end:
            msg = bus.recv(0.5)
            if msg is not None and msg.data[0] & 0xE0 == 0x00:  # download segment request
                segments += 1
                if segments >= 20:
                    return
    raise AssertionError("no segmented download seen")


def thawed_status(channel: str, within_s: float = 15.0):
    """The device's status, asked again while it does not answer (a device just thawed)."""
    from canical.device.sdo_download import DeviceSilent

    deadline = time.monotonic() + within_s
    while True:
        try:
            with client(channel, timeout=2.0) as c:
                return c.status()
        except DeviceSilent:
            if time.monotonic() > deadline:
                raise
            time.sleep(0.5)


@pytest.mark.vcan
def test_sdo_timeout_when_the_device_freezes(vcan_channel: str, tmp_path: Path) -> None:
    with device(vcan_channel, tmp_path, "--rate", "50") as dev:
        proc = _second_push_mid_download(vcan_channel, tmp_path)
        assert dev.proc is not None
        dev.proc.send_signal(signal.SIGSTOP)
        try:
            out, err = proc.communicate(timeout=60)
        finally:
            dev.proc.send_signal(signal.SIGCONT)
        assert_one_line_error(subprocess.CompletedProcess(proc.args, proc.returncode, out, err),
                              "no answer while", "after 1 s")
        # Just thawed, the device first works off what queued meanwhile, and reopens its bus if
        # its receive queue overflowed: asked again until it answers (15 s at most).
        assert thawed_status(vcan_channel).active_ids == ids(0)
        time.sleep(5.5)  # the dead tool's lock lease runs out; then a push goes through
        assert canical("push", *proc.args[4:]).returncode == 0  # the interrupted push, again


@pytest.mark.vcan
def test_two_pushes_at_once(vcan_channel: str, tmp_path: Path) -> None:
    """A second tool meets the first one's download lock; racing tools never leave a mix.

    Whether two processes started together really overlap depends on the machine
    (in the test kernel one start-up takes longer than a whole push), so the lock
    is first held deterministically, as another tool in mid-download holds it;
    then two pushes race and either both finish one after the other or one is
    refused, and the device runs one whole set.
    """
    paths = [write_sets(tmp_path / f"s{f}", family=f) for f in (0, 1, 2)]
    with device(vcan_channel, tmp_path, "--rate", "50"):
        assert canical("push", *paths[0], *bus_args(vcan_channel)).returncode == 0
        lock = imu_objects().download_lock
        done = threading.Event()

        def hold_lock() -> None:
            # Another tool mid-download renews its lease (5 s) as it writes.
            with client(vcan_channel) as c:
                while not done.is_set():
                    c.write_uint(lock, 0x5EC0_0001, 4, "holding the lock as another tool")
                    done.wait(1.5)
                c.write_uint(lock, 0, 4, "releasing the lock")

        holder = threading.Thread(target=hold_lock)
        holder.start()
        try:
            time.sleep(0.5)
            held = canical("push", *paths[1], *bus_args(vcan_channel))
        finally:
            done.set()
            holder.join(30)
        with client(vcan_channel) as c:
            assert c.status().active_ids == ids(0)  # the refused push changed nothing
        assert held.returncode == 2, held.stderr
        assert len(held.stderr.strip().splitlines()) == 1 and "Traceback" not in held.stderr, held.stderr

        procs = [subprocess.Popen([sys.executable, "-m", "canical", "push", *p, *bus_args(vcan_channel)],
                                  stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
                 for p in paths[1:]]
        results = [(p.wait(120), *p.communicate()) for p in procs]
        with client(vcan_channel) as c:
            running = c.status().active_ids
    for code, _out, err in results:
        assert code in (0, 2), err
        if code:
            assert len(err.strip().splitlines()) == 1 and "Traceback" not in err, err
    assert running in (ids(0), ids(1), ids(2))  # a whole set, never a mix
    winners = [family for family, (code, _o, _e) in zip((1, 2), results, strict=True) if code == 0]
    if len(winners) == 1:
        assert running == ids(winners[0])
    elif winners:
        assert running in (ids(1), ids(2))  # they ran one after the other


def _timed_push(channel: str, family: int, started: threading.Event | None = None) -> float:
    """Push the three-axis set ``family``; return how long the push itself took, in seconds (not
    opening and closing the client, which take as long again in the guest). ``started`` is set
    when the push begins."""
    sets = {a: (a, s) for a, s in imu_sets(family).items()}
    with client(channel) as c:
        if started is not None:
            started.set()
        t0 = time.monotonic()
        push_sets(c, sets)
        return time.monotonic() - t0


@pytest.mark.vcan
def test_many_interrupted_downloads_zero_partial_activations(vcan_channel: str, tmp_path: Path) -> None:
    """Kill the device at random moments of a three-axis push, power it up again, look at what
    it runs: always all of the old set or all of the new one, every bank it runs valid."""
    rng = random.Random(5)
    # SDO only (no raw stream): 21 power-ups stay quick; the single-kill test above streams.
    dev = Device(vcan_channel, tmp_path / "imu.json", "--rate", "0").start()
    outcomes = {"old": 0, "new": 0, "partial": 0}
    steps: dict[str, int] = {}
    try:
        # A new family each push, so that every push downloads all banks (a push skips the banks
        # that already hold its set, as after a killed push). Kills are timed against the quickest
        # of three warm pushes (a fresh guest's first push is slower), from the push's start.
        full = min(_timed_push(vcan_channel, family) for family in (0, 1, 2))
        current = 2
        for target in range(3, 23):
            ids(target)  # its sets are made before the push starts, not inside its time
            errors: list[Exception] = []
            started = threading.Event()

            def push(target=target, errors=errors, started=started) -> None:
                try:
                    _timed_push(vcan_channel, target, started)
                except CanicalError as exc:
                    errors.append(exc)

            thread = threading.Thread(target=push)
            thread.start()
            assert started.wait(30), "the push did not start"
            time.sleep(rng.uniform(0.05, 0.9 * full))
            dev.kill()
            thread.join(60)
            step = "completed" if not errors else str(errors[0]).split(" while ")[-1].split(" (")[0]
            steps[step] = steps.get(step, 0) + 1
            dev.start()
            with client(vcan_channel) as c:
                status = c.status()
                valid = all(c.bank(a, status.active[a])[2] == 1 for a in AXES)  # type: ignore[arg-type]
            if status.active_ids == ids(current) and valid:
                outcomes["old"] += 1
            elif status.active_ids == ids(target) and valid:
                outcomes["new"] += 1
                current = target
            else:
                outcomes["partial"] += 1
        print(f"\n20 interrupted three-axis pushes (uninterrupted: {full:.2f} s): {outcomes}; "
              f"where the tool was when the device died: {steps}")
    finally:
        dev.stop()
    assert outcomes["partial"] == 0
    mid_download = sum(n for s, n in steps.items() if s.startswith(("downloading", "writing the CRC")))
    assert mid_download >= 5, steps  # most kills land inside a bank download


@pytest.mark.vcan
def test_whole_loop_on_vcan_device_corrects_like_apply(vcan_channel: str, tmp_path: Path) -> None:
    """Session recorded from the device, calibrated, pushed; the device's corrected frames
    equal `canical apply` on the same raw frames to the frame's resolution."""
    from canical.commands.demo_bus import BusDemoOptions, run_bus_demo

    rates = "-60:60:10"
    options = BusDemoOptions(interface="socketcan", channel=vcan_channel, node_id=NODE, serial=SERIAL,
                             sample_rate_hz=40.0, speed=2.0, dwell_s=2.0, field_samples=200, emulate=False,
                             field_pass=None,
                             table_rates=tuple(float(r) for r in range(-60, 61, 10)))
    with device(vcan_channel, tmp_path, "--rate", "40", "--speed", "2", f"--table-rates={rates}",
                "--dwell", "2", "--correct") as dev:
        result = run_bus_demo(tmp_path / "loop", options, say=print)
    assert result.max_device_vs_apply_dps <= 0.0051
    # the device ran the firmware's C evaluator (firmware/canical_eval.c), not Python
    assert "corrected on the device with the firmware evaluator (C)" in dev.log.read_text()
    assert result.field_samples >= 200
    assert result.push.status.active_ids["z"] == result.set_id


@pytest.mark.vcan
def test_daemon_takes_its_sets_from_the_device_and_falls_back_to_files(vcan_channel: str,
                                                                        tmp_path: Path) -> None:
    """config ``device``: the daemon's start (and SIGHUP) reads the IMU's active sets over SDO;
    an axis the device cannot give, or a silent device, falls back to the configured file."""
    from canical.bus import active_sets
    from canical.bus.daemon_config import load_config

    try:
        from support.daemon_fixtures import write_config
    except ImportError:  # pragma: no cover
        from tests.daemon_fixtures import write_config  # type: ignore[no-redef]

    files = tmp_path / "etc"
    files.mkdir()
    for axis, cset in imu_sets(1).items():
        coefficient_file.save(files / f"imu-{axis}.yaml", cset)
    config = load_config(write_config(files, vcan_channel, sensor=str(SERIAL),
                                      device={"node": 0x10, "timeout_s": 0.5}))
    node10 = Device(vcan_channel, tmp_path / "imu.json", "--rate", "0", node=0x10)  # as the DBC has it
    try:
        node10.start()
        with client(vcan_channel, node=0x10) as c:
            push_sets(c, {"x": ("x", imu_set("x", 0)), "z": ("z", imu_set("z", 0))})
        sets, messages = active_sets.initial(config)
        assert [(a.axis, a.source, a.set_id) for a in sets.axes] == [
            ("x", active_sets.SOURCE_DEVICE, ids(0)["x"]),
            ("y", active_sets.SOURCE_FILE, ids(1)["y"]),  # the device has no set for y
            ("z", active_sets.SOURCE_DEVICE, ids(0)["z"]),
        ]
        with client(vcan_channel, node=0x10) as c:
            push_sets(c, {"z": ("z", imu_set("z", 2))})
        after_hup, messages = active_sets.from_device(config, sets)  # what SIGHUP does
        assert after_hup.axes[2].set_id == ids(2)["z"]
        assert after_hup.axes[0].corrector is sets.axes[0].corrector  # unchanged: kept, with its state
        assert any("from device node 0x10 replaces" in m.text for m in messages)
        node10.stop()
        silent, messages = active_sets.initial(config)
        assert [(a.source, a.set_id) for a in silent.axes] == [
            (active_sets.SOURCE_FILE, ids(1)[a]) for a in AXES]
        assert any("device node 0x10" in m.text and "no answer" in m.text
                   and "using the coefficient files" in m.text for m in messages)
    finally:
        node10.stop()


@pytest.mark.vcan
def test_imu_set_push_pull_round_trip_survives_power_cycle(vcan_channel: str, tmp_path: Path) -> None:
    """An IMU set (three axes and their coupling) pushed to the device process over SocketCAN:
    activated in one write, applied by the firmware evaluator, stored, and pulled back after a
    power cut as the very set pushed."""
    from canical.sets import imu_set as imu_file

    try:
        from support.imu_fixtures import imu_triad_set
    except ImportError:  # pragma: no cover
        from tests.imu_fixtures import imu_triad_set  # type: ignore[no-redef]

    imu = imu_triad_set(0)
    path, back = tmp_path / "imu.yaml", tmp_path / "back.yaml"
    imu_file.save(path, imu)
    with device(vcan_channel, tmp_path, "--rate", "50", "--correct") as dev:
        pushed = canical("push", str(path), *bus_args(vcan_channel))
        assert pushed.returncode == 0, pushed.stderr
        assert f"coupling of IMU set 0x{imu_file.imu_set_crc(imu):08x}" in pushed.stdout
        assert "stored for power-up" in pushed.stdout
        deadline = time.monotonic() + 20.0
        while "coupling applied on the device with the firmware evaluator (C)" not in dev.log.read_text():
            assert time.monotonic() < deadline, dev.log.read_text()[-2000:]
            time.sleep(0.2)
        dev.kill()  # power cut: the stored IMU set must come back
        dev.start()
        pulled = canical("pull", *bus_args(vcan_channel), "--imu-set", "-o", str(back))
        assert pulled.returncode == 0, pulled.stderr
    again = imu_file.load(back)
    assert again == imu and imu_file.imu_set_crc(again) == imu_file.imu_set_crc(imu)


def answers_in_order(msgs: list, raw_id: int, answer_id: int) -> dict[int, object]:
    """Each ``answer_id`` frame by the raw frame (its index among the raw frames) it answers, for
    a sender that answers every raw frame once and in order: the k-th answer is the answer to raw
    frame j0 + k, j0 the latest first raw frame such that every answer follows its raw frame."""
    import numpy as np

    raw_at = np.array([i for i, m in enumerate(msgs) if m.arbitration_id == raw_id])
    answers = [(i, m) for i, m in enumerate(msgs) if m.arbitration_id == answer_id]
    answer_at = np.array([i for i, _ in answers])
    causal = [j0 for j0 in range(raw_at.size - answer_at.size + 1)
              if np.all(raw_at[j0:j0 + answer_at.size] < answer_at)]
    assert causal, "the answers are more than the raw frames before them"
    return {causal[-1] + k: m for k, (_, m) in enumerate(answers)}


def test_answers_are_paired_in_order_though_one_comes_after_the_next_raw_frame() -> None:
    """A daemon bound after the first raw frame, one answer late (after the next raw frame) and
    two back to back: each answer still goes to its own raw frame, not to the one before it."""
    from types import SimpleNamespace

    order = "RRARARRAARA"
    msgs = [SimpleNamespace(arbitration_id=1 if k == "R" else 2, at=i) for i, k in enumerate(order)]
    paired = {raw: m.at for raw, m in answers_in_order(msgs, 1, 2).items()}
    assert paired == {1: 2, 2: 4, 3: 7, 4: 8, 5: 10}


@pytest.mark.vcan
def test_device_daemon_and_apply_agree_with_an_imu_set(vcan_channel: str, tmp_path: Path) -> None:
    """An IMU set pushed to the device process; the daemon (``device:``) takes it from the device;
    on the same raw frames the device's IMU_RATE, the daemon's CANICAL_RATE and ``apply imu.yaml``
    on a log of the bus agree to the frames' resolution, on all three coupled axes."""
    import numpy as np

    from canical.frames.codec import load_dbc
    from canical.sessions.csv_file import read_table
    from canical.sets import imu_set as imu_file

    try:
        from support.daemon_fixtures import DBC, DaemonProcess, Recorder, write_config
        from support.imu_fixtures import imu_triad_set
    except ImportError:  # pragma: no cover
        from tests.daemon_fixtures import DBC, DaemonProcess, Recorder, write_config  # type: ignore[no-redef]
        from tests.imu_fixtures import imu_triad_set  # type: ignore[no-redef]

    imu = imu_triad_set(0, str(SERIAL))
    path = tmp_path / "imu.yaml"
    imu_file.save(path, imu)
    etc = tmp_path / "etc"
    etc.mkdir()
    imu_file.save(etc / "imu.yaml", imu_triad_set(1, str(SERIAL)))  # the file, until the device answers
    config = write_config(etc, vcan_channel, sensor=str(SERIAL), inputs={},
                          axes={a: {"raw": f"GyroRaw{a.upper()}"} for a in AXES},
                          imu_set=str(etc / "imu.yaml"), device={"node": 0x10, "timeout_s": 1.0})
    db = load_dbc(DBC)
    raw_id, dev_id, rate_id = (db.get_message_by_name(m).frame_id
                               for m in ("IMU_RAW", "IMU_RATE", "CANICAL_RATE"))
    node = Device(vcan_channel, tmp_path / "dev.json", "--rate", "50", "--correct", "--table-rates=-45:45:15",
                  "--dwell", "1", node=0x10)
    try:
        node.start()
        pushed = canical("push", str(path), "--node", "0x10", "--channel", vcan_channel, "--timeout", TIMEOUT)
        assert pushed.returncode == 0, pushed.stderr
        rec = Recorder(vcan_channel)
        daemon = DaemonProcess(config)
        try:
            rec.wait_count(rate_id, 400, timeout=60)
        finally:
            daemon.stop()
            msgs = list(rec.messages)
            rec.close()
    finally:
        node.stop()
    assert f"imu set 0x{imu_file.imu_set_crc(imu):08x} from device node 0x10" in daemon.log(), daemon.log()
    # Frame by frame: the device sends its corrected frame right after its raw one; the daemon
    # answers every raw frame in order, not always before the next one arrives (a loaded machine).
    rows, raw_seen, dev_of = [], None, {}
    for m in msgs:
        if m.arbitration_id == raw_id:
            raw_seen = len(rows)
            rows.append(m)
        elif m.arbitration_id == dev_id and raw_seen is not None:
            dev_of.setdefault(raw_seen, m)
    ours_of = answers_in_order(msgs, raw_id, rate_id)
    both = sorted(set(dev_of) & set(ours_of))
    assert len(both) >= 300
    dev_msg, rate_msg = db.get_message_by_name("IMU_RATE"), db.get_message_by_name("CANICAL_RATE")
    log = tmp_path / "bus.log"
    import can

    with can.Logger(str(log)) as logger:
        for m in msgs:
            if m.arbitration_id in (raw_id, db.get_message_by_name("IMU_AUX").frame_id):
                logger.on_message_received(m)
    out = tmp_path / "apply.csv"
    applied = canical("apply", str(path), str(log), "--config", str(config), "-o", str(out))
    assert applied.returncode == 0, applied.stderr
    table = read_table(out).columns
    for axis in AXES:
        dev = np.array([dev_msg.decode(dev_of[i].data)[f"Rate{axis.upper()}"] for i in both])
        ours = np.array([rate_msg.decode(ours_of[i].data)[f"Rate{axis.upper()}"] for i in both])
        want = np.clip(table[f"rate_{axis}_dps"][both], -327.68, 327.67)
        assert np.max(np.abs(ours - want)) <= 0.0051, axis
        assert np.max(np.abs(dev - want)) <= 0.0101, axis  # the device's float32 and its own rounding
