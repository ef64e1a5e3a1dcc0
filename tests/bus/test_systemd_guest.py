"""The shipped units under a real systemd: install, start, notify, reload, watchdog, sandbox.

These run inside a User-mode Linux guest that boots the host's ``/lib/systemd/systemd`` as
PID 1 (read-only host root under a tmpfs overlay; ``tests/support/vcan_harness.py``); pytest itself
runs there as a oneshot unit. canical is installed the way a vehicle gets it, with
``canical install-service`` from a wheel built on the host, so the units run exactly as
shipped: a dynamic user that sees neither this test venv nor ``/root``.

The tests share one systemd and run in file order; each leaves the canical units stopped.
"""

from __future__ import annotations

import json
import os
import signal
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from support.daemon_fixtures import (
    DBC,
    Recorder,
    decode_stream,
    expected_rates,
    imu_stream,
    send_paced,
    write_sets,
)
from support.systemd_guest import (
    ENV_WHEEL,
    ENV_WHEELHOUSE,
    drop_in,
    journal,
    remove_drop_ins,
    run,
    show,
    systemctl,
    wait_until,
)

from canical.bus.active_sets import AxisSet, build
from canical.frames.codec import load_dbc
from canical.sessions.csv_file import read_table
from canical.sets import coefficient_file
from canical.sets.corrector import Corrector

pytestmark = [pytest.mark.vcan, pytest.mark.systemd_guest]

DAEMON = "canical@vcan0.service"
EMULATOR = "canical-imu-emulator@vcan0.service"
ETC = Path("/etc/canical")
PROBE = Path("/opt/canical/sandbox_probe.py")
RATE_HZ = 300.0
HALF_LSB = 0.005 + 1e-9

PROBE_SOURCE = '''
import json, os, socket
def refused(family, kind, proto=0):
    try:
        socket.socket(family, kind, proto).close()
    except OSError as exc:
        return exc.errno
    return 0
lines = open("/proc/self/status").read().splitlines()
status = dict(line.split(":\\t", 1) for line in lines if ":\\t" in line)
can = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
can.bind(("vcan0",))
can.close()
def listing(path):
    try:
        return os.listdir(path)
    except OSError as exc:
        return exc.errno
print("canical-sandbox-probe " + json.dumps({
    "uid": os.getuid(), "no_new_privs": status["NoNewPrivs"].strip(), "seccomp": status["Seccomp"].strip(),
    "af_inet": refused(socket.AF_INET, socket.SOCK_DGRAM),
    "af_inet6": refused(socket.AF_INET6, socket.SOCK_STREAM),
    "af_netlink": refused(socket.AF_NETLINK, socket.SOCK_RAW, 0), "af_can": "ok",
    "etc_ro": bool(os.statvfs("/etc").f_flag & os.ST_RDONLY),
    "usr_ro": bool(os.statvfs("/usr").f_flag & os.ST_RDONLY),
    "home": listing("/home"), "root": listing("/root"),
    "pyenv_visible": os.path.exists("/root/.pyenv"),
}), flush=True)
'''


@pytest.fixture(scope="module")
def db():
    return load_dbc(DBC)


@pytest.fixture(scope="module")
def installed(tmp_path_factory: pytest.TempPathFactory) -> dict[str, object]:
    """canical installed from the wheel: first run, a second (idempotent) and a dry run."""
    assert os.environ.get(ENV_WHEEL), "the host did not build a wheel for the systemd guest"
    folder = tmp_path_factory.mktemp("sets")
    paths = write_sets(folder)
    cmd = [sys.executable, "-m", "canical", "install-service", "--wheel", os.environ[ENV_WHEEL],
           "--no-index", "--find-links", os.environ[ENV_WHEELHOUSE], "--channel", "vcan0",
           *(arg for axis in ("x", "y", "z") for arg in ("--set", str(paths[axis])))]
    start = time.monotonic()
    first = run(*cmd, timeout=900)
    took = time.monotonic() - start
    second = run(*cmd)
    variant = tmp_path_factory.mktemp("variant")
    changed = write_sets(variant, variant=1)
    dry = run(*cmd[:-6], "--set", str(changed["x"]), "--dry-run")
    # Reloads only on SIGHUP in these tests (no file watching racing it).
    config = ETC / "vcan0.yaml"
    text = config.read_text()
    assert "watch_period_s: 1.0" in text
    config.write_text(text.replace("watch_period_s: 1.0", "watch_period_s: 3600"))
    PROBE.write_text(PROBE_SOURCE)
    PROBE.chmod(0o644)
    return {"first": first.stdout, "second": second.stdout, "dry": dry.stdout, "took": took,
            "sets": paths, "variant": changed, "variant_folder": variant, "cmd": cmd}


@pytest.fixture(autouse=True)
def units_stopped():
    """Every test starts and ends with the canical units stopped, reset and without drop-ins."""
    yield
    units = (DAEMON, EMULATOR, "canical@vcan1.service")
    systemctl("stop", *units, check=False)  # one call each: every systemctl costs ~1 s in UML
    systemctl("reset-failed", *units, check=False)
    remove_drop_ins(DAEMON, EMULATOR)
    if "UP" not in run("ip", "-brief", "link", "show", "vcan0").stdout:
        run("ip", "link", "set", "vcan0", "up")


def _start_watching_readiness(unit: str) -> list[tuple[str, str, str]]:
    """Start without waiting; the (ActiveState, SubState, MainPID) seen until active."""
    systemctl("start", "--no-block", unit)
    seen: list[tuple[str, str, str]] = []

    def active() -> bool:
        p = show(unit, "ActiveState", "SubState", "MainPID")
        state = (p["ActiveState"], p["SubState"], p["MainPID"])
        if not seen or seen[-1] != state:
            seen.append(state)
        assert p["ActiveState"] != "failed", (seen, journal(unit)[-20:])
        return p["ActiveState"] == "active"

    wait_until(f"{unit} active", active, timeout=90, step=0.05)
    return seen


def _status_text(unit: str = DAEMON) -> str:
    return show(unit, "StatusText")["StatusText"]


def _since_last_start(lines: list[str]) -> list[str]:
    """The daemon's journal lines from its latest start (its "ready on" line) on."""
    starts = [i for i, line in enumerate(lines) if line.startswith("INFO ready on ")]
    return lines[starts[-1]:] if starts else lines


def _status_when(predicate) -> str | None:
    """The daemon's StatusText if ``predicate`` holds for it, else None."""
    text = _status_text()
    return text if predicate(text) else None


def _frames_in(status: str) -> int:
    """'running: 123 frames in, ...' -> 123."""
    head = status.split(" frames in", 1)[0]
    return int(head.rsplit(" ", 1)[-1]) if " frames in" in status else -1


def _write_canlog(path: Path, msgs) -> None:
    import can

    with can.Logger(str(path)) as logger:
        for m in msgs:
            logger.on_message_received(m)


def test_install_service_from_wheel(installed) -> None:
    """A venv under /opt on the system Python, the unit's /usr/local/bin/canical, /etc/canical
    world-readable; a second run changes nothing; a dry run only says what it would do."""
    print(f"install-service from the wheel took {installed['took']:.1f} s")
    cfg = Path("/opt/canical/venv/pyvenv.cfg").read_text()
    assert "home = /usr/bin" in cfg, cfg
    assert os.readlink("/usr/local/bin/canical") == "/opt/canical/venv/bin/canical"
    for name in ("canical.dbc", "vcan0.yaml", "imu-x.yaml", "imu-y.yaml", "imu-z.yaml"):
        assert (ETC / name).stat().st_mode & 0o777 == 0o644, name
    assert ETC.stat().st_mode & 0o777 == 0o755
    for unit in ("canical@.service", "canical-can@.service", "canical-imu-emulator@.service"):
        assert Path("/etc/systemd/system", unit).is_file()
    assert "channel: vcan0" in (ETC / "vcan0.yaml").read_text()
    assert installed["second"].strip() == "canical service: already installed, nothing to do"
    dry = installed["dry"].splitlines()
    assert dry == [f"would write {ETC}/imu-x.yaml (axis x set from {installed['variant']['x']})"], dry
    assert (ETC / "imu-x.yaml").read_bytes() == Path(installed["sets"]["x"]).read_bytes()
    version = run("/usr/local/bin/canical", "--version").stdout
    assert version.startswith("canical "), version


def test_start_ready_status_and_frames_like_apply(installed, db, tmp_path: Path) -> None:
    """Active only once READY=1 arrived (activating meanwhile, with a main PID); the corrected
    frames equal ``canical apply`` on the same samples; STATUS counts an emulated IMU's frames."""
    rec = Recorder("vcan0")
    try:
        seen = _start_watching_readiness(DAEMON)
        assert any(s[0] == "activating" and s[2] != "0" for s in seen), seen
        assert seen[-1][:2] == ("active", "running"), seen
        # The interface unit it Wants= came up on a vcan (no bit timing, no device unit).
        iface = show("canical-can@vcan0.service", "ActiveState", "SubState", "Result")
        assert iface == {"ActiveState": "active", "SubState": "exited", "Result": "success"}, iface
        assert _status_text().startswith("running: 0 frames in"), _status_text()

        stream = imu_stream(600)
        import can

        with can.Bus(interface="socketcan", channel="vcan0") as tx:
            send_paced(tx, stream.frames, RATE_HZ)
        rate_id = db.get_message_by_name("CANICAL_RATE").frame_id
        out = rec.wait_count(rate_id, len(stream.raw_index), timeout=30)
        msgs = list(rec.messages)
    finally:
        rec.close()
    assert len(out) == len(stream.raw_index)
    log = tmp_path / "drive.log"
    _write_canlog(log, [m for m in msgs if m.arbitration_id in (0x190, 0x290)])
    rate_msg = db.get_message_by_name("CANICAL_RATE")
    got = [rate_msg.decode(bytes(m.data), decode_choices=False) for m in out]
    for axis in ("x", "y", "z"):
        csv = tmp_path / f"apply-{axis}.csv"
        run("/usr/local/bin/canical", "apply", str(ETC / f"imu-{axis}.yaml"), str(log),
            "--config", str(ETC / "vcan0.yaml"), "-o", str(csv))
        table = read_table(csv).columns
        expected = np.clip(table["rate_dps"], -327.68, 327.67)
        sent = np.array([g[f"Rate{axis.upper()}"] for g in got])
        assert len(sent) == len(expected)
        assert np.max(np.abs(sent - expected)) <= HALF_LSB, axis

    systemctl("start", EMULATOR)
    before = _frames_in(_status_text())
    status = wait_until("STATUS counting the emulator's frames",
                        lambda: _status_when(lambda s: _frames_in(s) > before + 50), timeout=30)
    assert str(status).startswith("running: "), status
    assert show(EMULATOR, "ActiveState")["ActiveState"] == "active"


def test_reload_keeps_pid_and_uses_new_sets_from_next_frame(installed, db) -> None:
    """``systemctl reload``: same main PID; once adopted, every frame carries the new sets'
    tag and their rates."""
    systemctl("start", DAEMON)
    pid = show(DAEMON, "MainPID")["MainPID"]
    new = installed["variant"]
    ids = {axis: Corrector(coefficient_file.load(new[axis])).set_id for axis in ("x", "y", "z")}
    want = " ".join(f"{axis}={ids[axis]:08x}" for axis in ("x", "y", "z"))
    run(*installed["cmd"][:-6], *(a for axis in ("x", "y", "z") for a in ("--set", str(new[axis]))))
    systemctl("reload", DAEMON)
    wait_until("the new sets in STATUS", lambda: want in _status_text(), timeout=30)
    assert show(DAEMON, "MainPID")["MainPID"] == pid
    assert any("(SIGHUP)" in line for line in journal(DAEMON))

    tag = build(tuple(AxisSet(axis=a, raw_signal="", set_id=ids[a]) for a in ("x", "y", "z"))).tag
    stream = imu_stream(200, seed=5)
    rec = Recorder("vcan0")
    try:
        import can

        with can.Bus(interface="socketcan", channel="vcan0") as tx:
            send_paced(tx, stream.frames, RATE_HZ)
        out = rec.wait_count(db.get_message_by_name("CANICAL_RATE").frame_id, 200, timeout=30)
    finally:
        rec.close()
    rate_msg = db.get_message_by_name("CANICAL_RATE")
    got = [rate_msg.decode(bytes(m.data), decode_choices=False) for m in out]
    assert len(got) == 200 and all(g["SetTag"] == tag for g in got)
    expected = expected_rates(decode_stream(stream), new)
    for axis in ("x", "y", "z"):
        sent = np.array([g[f"Rate{axis.upper()}"] for g in got])
        assert np.max(np.abs(sent - expected[axis])) <= HALF_LSB, axis
    # put the original sets back for the tests after this one
    run(*installed["cmd"])


def test_watchdog_kills_a_stopped_daemon_and_restarts_it(installed) -> None:
    """SIGSTOP the main PID: no more pings, systemd's watchdog kills it (Result=watchdog) and
    Restart=on-failure brings it back (NRestarts=1)."""
    systemctl("start", DAEMON)
    pid = int(show(DAEMON, "MainPID")["MainPID"])
    os.kill(pid, signal.SIGSTOP)
    wait_until("the watchdog restart", lambda: show(DAEMON, "NRestarts")["NRestarts"] == "1", timeout=60)
    wait_until("active again", lambda: show(DAEMON, "ActiveState")["ActiveState"] == "active", timeout=90)
    assert int(show(DAEMON, "MainPID")["MainPID"]) not in (0, pid)
    lines = journal(DAEMON)  # the only watchdog kill in this guest's life
    keys = ("atchdog", "Killing process", "Main process exited", "Scheduled restart")
    proof = [line for line in lines if any(k in line for k in keys)]
    print("journal:\n" + "\n".join(proof))
    assert any("Watchdog timeout" in line for line in proof), lines
    assert any("'watchdog'" in line for line in lines), lines  # "Failed with result 'watchdog'"
    assert any("Scheduled restart job, restart counter is at 1" in line for line in proof), lines


def test_bad_configuration_exits_2_and_is_not_restarted(installed) -> None:
    """A typo in /etc/canical/vcan1.yaml: exit status 2, not restarted, one line saying where."""
    text = (ETC / "vcan0.yaml").read_text().replace("channel: vcan0", "chanel: vcan1")
    (ETC / "vcan1.yaml").write_text(text)
    (ETC / "vcan1.yaml").chmod(0o644)
    unit = "canical@vcan1.service"
    systemctl("start", unit, check=False)
    wait_until(f"{unit} failed", lambda: show(unit, "ActiveState")["ActiveState"] == "failed", timeout=60)
    time.sleep(2.0)  # longer than RestartSec: a restart would have happened by now
    props = show(unit, "ActiveState", "ExecMainStatus", "NRestarts", "Result")
    assert props == {"ActiveState": "failed", "ExecMainStatus": "2", "NRestarts": "0",
                     "Result": "exit-code"}, props
    errors = [line for line in journal(unit) if "error" in line]
    print("journal:\n" + "\n".join(errors))
    assert errors == ["canical serve: error: /etc/canical/vcan1.yaml: bus.chanel: unknown key "
                      "(expected one of channel, interface, options)"], errors


def test_stop_is_clean_and_prompt(installed) -> None:
    systemctl("start", DAEMON)
    start = time.monotonic()
    systemctl("stop", DAEMON)
    took = time.monotonic() - start
    timeout = show(DAEMON, "TimeoutStopUSec")["TimeoutStopUSec"]
    props = show(DAEMON, "ActiveState", "Result", "ExecMainStatus")
    print(f"systemctl stop took {took:.1f} s (TimeoutStopSec {timeout})")
    assert props == {"ActiveState": "inactive", "Result": "success", "ExecMainStatus": "0"}, props
    assert took < 10.0
    assert any(line.startswith("INFO stopped: stopping:") for line in journal(DAEMON)), journal(DAEMON)


@pytest.mark.parametrize("unit", [DAEMON, EMULATOR])
def test_sandbox_is_in_force(installed, unit: str) -> None:
    """An ExecStartPre= probe, in the unit's own sandbox: dynamic user, no new privileges,
    seccomp, no AF_INET/AF_INET6/AF_NETLINK, /etc and /usr read-only, /home and /root hidden;
    AF_CAN works."""
    drop_in(unit, "probe", f"[Service]\nExecStartPre=/opt/canical/venv/bin/python {PROBE}\n")
    systemctl("start", unit)
    lines = [line for line in journal(unit) if "canical-sandbox-probe" in line]
    assert lines, journal(unit)[-20:]
    print("journal:\n" + lines[-1])
    seen = json.loads(lines[-1].split("canical-sandbox-probe ", 1)[1])
    assert 61184 <= seen["uid"] <= 65519, seen  # systemd's range for dynamic users
    assert seen["no_new_privs"] == "1" and seen["seccomp"] == "2", seen
    eafnosupport = 97
    assert seen["af_inet"] == seen["af_inet6"] == seen["af_netlink"] == eafnosupport, seen
    assert seen["af_can"] == "ok" and seen["etc_ro"] and seen["usr_ro"], seen
    assert seen["home"] in ([], 13) and seen["root"] in ([], 13) and not seen["pyenv_visible"], seen


def test_bus_loss_under_systemd(installed) -> None:
    """vcan0 down for 3 s while the emulated IMU streams: the service stays active (same PID, no
    restart, the watchdog kept), says so in STATUS, and counts frames again once it is back."""
    systemctl("start", DAEMON)
    systemctl("start", EMULATOR)
    pid = show(DAEMON, "MainPID")["MainPID"]
    wait_until("frames flowing", lambda: _frames_in(_status_text()) > 50, timeout=30)
    run("ip", "link", "set", "vcan0", "down")
    down_status = wait_until("STATUS saying vcan0 is down",
                             lambda: _status_when(lambda s: "vcan0 down for" in s), timeout=5)
    time.sleep(3.0)
    run("ip", "link", "set", "vcan0", "up")
    wait_until("STATUS without the outage", lambda: "down for" not in _status_text(), timeout=10)
    after = _frames_in(_status_text())
    wait_until("frames counted again", lambda: _frames_in(_status_text()) > after + 20, timeout=30)
    props = show(DAEMON, "ActiveState", "MainPID", "NRestarts")
    assert props == {"ActiveState": "active", "MainPID": pid, "NRestarts": "0"}, props
    lines = _since_last_start(journal(DAEMON))
    print("STATUS during the outage: " + str(down_status))
    print("journal:\n" + "\n".join(lines))
    outage = [line for line in lines if "vcan0" in line and ("lost" in line or "back after" in line)]
    assert len(outage) == 2 and "lost" in outage[0] and "back after" in outage[1], lines


def test_trust_under_the_sandbox(installed, tmp_path: Path) -> None:
    """``trust: require`` in the hardened unit: the service's dynamic user reads the lab's public
    key and the signed sets from /etc/canical; an unsigned set offered by ``systemctl reload`` is
    refused in one journal line and the running sets stay (STATUS, same PID); a newer signed set
    is adopted by the next reload."""
    from support.signed_sets import make_lab, signed_copy

    lab = make_lab(tmp_path / "keys")
    config = ETC / "vcan0.yaml"
    original = config.read_text()
    signed = {a: signed_copy(Path(p), tmp_path / f"v1-{a}.yaml", lab.key, 1)
              for a, p in installed["sets"].items()}
    newer_x = signed_copy(Path(installed["variant"]["x"]), tmp_path / "v2-x.yaml", lab.key, 2)

    def place(path: Path, source: Path) -> None:
        path.write_bytes(source.read_bytes())
        path.chmod(0o644)

    try:
        place(ETC / "lab.pub", lab.pub)
        for axis, path in signed.items():
            place(ETC / f"imu-{axis}.yaml", path)
        config.write_text(original + f"trust: {{keys: [{ETC}/lab.pub], require: true}}\n")
        systemctl("start", DAEMON)
        pid = show(DAEMON, "MainPID")["MainPID"]
        running = Corrector(coefficient_file.load(signed["x"])).set_id
        wait_until("STATUS with the signed sets", lambda: f"x={running:08x}" in _status_text(), timeout=30)
        place(ETC / "imu-x.yaml", Path(installed["variant"]["x"]))  # not signed
        systemctl("reload", DAEMON)
        refused = wait_until("the refusal in the journal", lambda: [
            line for line in _since_last_start(journal(DAEMON)) if "not signed" in line] or None, timeout=30)
        assert len(refused) == 1 and "keeping set" in refused[0], refused
        assert f"x={running:08x}" in _status_text() and show(DAEMON, "MainPID")["MainPID"] == pid
        place(ETC / "imu-x.yaml", newer_x)
        systemctl("reload", DAEMON)
        adopted = Corrector(coefficient_file.load(newer_x)).set_id
        wait_until("the newer signed set in STATUS", lambda: f"x={adopted:08x}" in _status_text(), timeout=30)
        assert show(DAEMON, "ActiveState", "MainPID") == {"ActiveState": "active", "MainPID": pid}
        print("journal:\n" + "\n".join(_since_last_start(journal(DAEMON))))
    finally:
        systemctl("stop", DAEMON, check=False)
        config.write_text(original)
        (ETC / "lab.pub").unlink(missing_ok=True)
        run(*installed["cmd"])  # the original sets back
