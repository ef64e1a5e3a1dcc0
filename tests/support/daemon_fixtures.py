"""Shared by the daemon tests and benchmarks: coefficient sets, configurations and IMU streams.

The configuration is always ``services/canical-can0.yaml`` (the deployable example) with its
``/etc/canical/`` paths pointed at a test folder and the channel replaced, so the example
is loaded by every daemon test and cannot rot.
"""

from __future__ import annotations

import dataclasses
import itertools
import os
import shutil
import signal
import socket
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from canical.bus.raw_bus import RawSocketBus
from canical.bus.socketcan import enlarge_socket_buffer
from canical.calibration.pipeline import CalibrateOptions, calibrate
from canical.frames.codec import load_dbc
from canical.frames.frame_match import FrameMatch
from canical.sets import coefficient_file
from canical.sets.coefficients import CoefficientSet
from canical.sets.terms import term_from_dict
from canical.sim.gyro import GyroModel
from canical.sim.sessions import paper_session

ROOT = Path(__file__).resolve().parents[2]
DBC = ROOT / "dbc" / "canical.dbc"
EXAMPLE_CONFIG = ROOT / "services" / "canical-can0.yaml"
SENSOR = "IMU-0001"
AXES = ("x", "y", "z")

#: Effect terms per axis, so every kind of term runs in the daemon: temperature and warm-up
#: on x, direction (stateful) on y, none on z.
TERMS = {
    "x": (
        {"kind": "channel", "channel": "temp_c", "feature": "offset", "form": "bias",
         "coefficient": 0.02, "reference": 25.0},
        {"kind": "time", "feature": "warmup", "form": "scale", "coefficient": -0.004, "tau_s": 30.0},
    ),
    "y": ({"kind": "direction", "feature": "sign", "form": "bias", "coefficient": 0.05,
           "threshold_raw": 200.0},),
    "z": (),
}


def base_set(axis: str, seed: int = 0) -> CoefficientSet:
    """A real calibration of a simulated sensor (fixed size, so it is quick)."""
    result = calibrate(paper_session(seed=seed), CalibrateOptions(segments=4, order=2),
                       sensor_id=SENSOR, axis=axis)
    return result.coefficients


#: Terms on every axis, every kind once: what the per-frame benchmarks correct with.
ALL_TERMS = {
    "x": TERMS["x"],
    "y": (*TERMS["y"], {"kind": "direction", "feature": "slope", "form": "scale", "coefficient": 1e-6,
                        "tau_s": 0.05}),
    "z": ({"kind": "channel", "channel": "supply_v", "feature": "square", "form": "scale",
           "coefficient": 0.001, "reference": 5.0},
          {"kind": "time", "feature": "linear", "form": "bias", "coefficient": 0.001}),
}


def write_sets(folder: Path, *, variant: int = 0, terms: dict | None = None,
               raw_units: str | None = None) -> dict[str, Path]:
    """imu-x/y/z.yaml with the TERMS (or ``terms``); ``variant`` shifts V0 (0.1 deg/s per step)
    so generations differ; ``raw_units`` (a vendor signal's unit) replaces the set's own."""
    paths = {}
    base = base_set("z")
    terms = TERMS if terms is None else terms
    for axis in AXES:
        typed = tuple(term_from_dict(t) if isinstance(t, dict) else t for t in terms[axis])
        cset = dataclasses.replace(base, axis=axis, terms=typed, v0=base.v0 + 40.0 * variant,
                                   raw_units=raw_units or base.raw_units)
        paths[axis] = folder / f"imu-{axis}.yaml"
        coefficient_file.save(paths[axis], cset)
    return paths


#: A triad's coupling (1–2 % cross-axis terms, scale errors on the diagonal) for the IMU sets below.
COUPLING = ((1.004, 0.012, -0.008), (0.015, 0.997, 0.004), (-0.02, 0.006, 1.002))


def write_imu_set(folder: Path, *, variant: int = 0, terms: dict | None = None,
                  coupling=COUPLING) -> Path:
    """imu-set.yaml: the sets of :func:`write_sets` (same ``variant`` and ``terms``) and ``coupling``,
    as one IMU set."""
    from canical.sets import imu_set

    sub = folder / f".axes-{variant}"
    sub.mkdir(exist_ok=True)
    paths = write_sets(sub, variant=variant, terms=terms)
    axes = tuple(coefficient_file.load(paths[a]) for a in AXES)
    imu = imu_set.ImuSet(SENSOR, axes, imu_set.as_matrix(coupling),  # type: ignore[arg-type]
                         imu_set.as_matrix(np.full((3, 3), 1e-4)), {}, "2026-01-01T00:00:00Z")
    path = folder / "imu-set.yaml"
    imu_set.save(path, imu)
    return path


def imu_set_config(folder: Path, channel: str, **overrides) -> Path:
    """:func:`write_config` correcting with ``folder``/imu-set.yaml (``imu_set``), no per-axis files."""
    axes = {a: {"raw": f"GyroRaw{a.upper()}"} for a in AXES}
    return write_config(folder, channel, axes=axes, imu_set=str(folder / "imu-set.yaml"), **overrides)


def write_config(folder: Path, channel: str, *, interface: str = "socketcan", **overrides) -> Path:
    """The deployable example, pointed at ``folder`` (DBC copied there) and ``channel``."""
    text = EXAMPLE_CONFIG.read_text().replace("/etc/canical/", f"{folder}/")
    content = yaml.safe_load(text)
    content["bus"]["interface"] = interface
    content["bus"]["channel"] = channel
    content.update(overrides)
    shutil.copyfile(DBC, folder / "canical.dbc")
    path = folder / f"{channel}.yaml"
    path.write_text(yaml.safe_dump(content, sort_keys=False))
    return path


@dataclass(frozen=True)
class Stream:
    """An IMU's frames in send order: raw frames, with an aux frame before every 10th."""

    frames: list[tuple[int, bytes]]  # (arbitration id, payload)
    raw_index: list[int]  # index in ``frames`` of each raw frame


def imu_stream(n: int, *, seed: int = 3, fs_hz: float = 200.0, uptime0_s: float = 5.0,
               first_counter: int = 0, rate_limit_dps: float = 75.0) -> Stream:
    """``n`` raw frames of a simulated IMU turning at rates that sweep past the calibrated span."""
    db = load_dbc(DBC)
    raw_msg = db.get_message_by_name("IMU_RAW")
    aux_msg = db.get_message_by_name("IMU_AUX")
    rng = np.random.default_rng(seed)
    t = np.arange(n) / fs_hz
    gyro = GyroModel()
    raws = {}
    for k, axis in enumerate(AXES):
        rate = rate_limit_dps * np.sin(2 * np.pi * (t / max(t[-1], 1e-9) + k / 3.0))
        raws[axis] = gyro.output(t, rate, rng=rng, fs_hz=fs_hz).astype(int)
    temp = 25.0 + 8.0 * np.sin(2 * np.pi * t / max(t[-1], 1e-9))
    frames: list[tuple[int, bytes]] = []
    raw_index: list[int] = []
    for i in range(n):
        if i % 10 == 0:
            frames.append((aux_msg.frame_id, aux_msg.encode({
                "SupplyVoltage": 5.0, "Uptime": round(uptime0_s + t[i], 3), "AuxCounter": (i // 10) & 0xF})))
        raw_index.append(len(frames))
        frames.append((raw_msg.frame_id, raw_msg.encode({
            "GyroRawX": int(raws["x"][i]), "GyroRawY": int(raws["y"][i]), "GyroRawZ": int(raws["z"][i]),
            "Temperature": round(float(temp[i]), 1), "Counter": (first_counter + i) & 0xF,
            "SensorFault": 0})))
    return Stream(frames, raw_index)


# ------------------------------------------------------------------------------------------
# Running the daemon as a separate process, and talking to it over a bus
# ------------------------------------------------------------------------------------------


def decode_stream(stream: Stream) -> list[dict[str, float]]:
    """Per raw frame, the signals the daemon would hold: the raw frame's, and IMU_AUX's latest."""
    db = load_dbc(DBC)
    raw_msg, aux_msg = db.get_message_by_name("IMU_RAW"), db.get_message_by_name("IMU_AUX")
    held: dict[str, float] = {}
    out = []
    for fid, data in stream.frames:
        if fid == aux_msg.frame_id:
            held.update(aux_msg.decode(data))
        else:
            out.append({**held, **raw_msg.decode(data)})
    return out


def expected_rates(signals: list[dict[str, float]], paths: dict[str, Path],
                   switches: tuple[tuple[int, dict[str, Path]], ...] = ()) -> dict[str, np.ndarray]:
    """What the daemon sends for these frames with one generation of sets, ``paths`` (one fresh
    Corrector per axis), or with ``switches``: from frame ``i`` of each ``(i, paths)`` on, the
    sets at those paths, where an axis whose set changed starts a fresh Corrector at frame ``i``
    (the direction, slope and lag state of a new set begins with it) and an axis whose set
    stayed carries on with its corrector and state, as the daemon does on a reload."""
    from canical.sets.corrector import Corrector

    out = {}
    for axis in AXES:
        schedule = dict(switches)
        text = paths[axis].read_bytes()
        corrector = Corrector(coefficient_file.load(paths[axis]))
        rates = []
        for i, s in enumerate(signals):
            if i in schedule and schedule[i][axis].read_bytes() != text:
                text = schedule[i][axis].read_bytes()
                corrector = Corrector(coefficient_file.load(schedule[i][axis]))
            inputs = {"temp_c": s["Temperature"], "time_s": s.get("Uptime", 0.0),
                      "supply_v": s.get("SupplyVoltage", 0.0)}
            rates.append(corrector.correct_one(s[f"GyroRaw{axis.upper()}"], inputs)[0])
        out[axis] = np.clip(np.asarray(rates), -327.68, 327.67)
    return out


class NotifyListener:
    """A stand-in for systemd's notify socket (abstract name): collects what the daemon says."""

    def __init__(self) -> None:
        self.name = f"@canical-test-{os.getpid()}-{next(_counter)}"
        self.sock = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        self.sock.bind(b"\0" + self.name[1:].encode())
        self.sock.settimeout(0.2)
        self.messages: list[dict[str, str]] = []
        self.arrived: dict[str, float] = {}  # time.monotonic() a key first came (READY: start-up time)
        self.times: list[float] = []  # time.monotonic() of each message's arrival
        self._stop = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop:
            try:
                data = self.sock.recv(4096)
            except TimeoutError:
                continue
            except OSError:
                return
            now = time.monotonic()
            fields = dict(line.split("=", 1) for line in data.decode().splitlines() if "=" in line)
            for key in fields:
                self.arrived.setdefault(key, now)
            self.times.append(now)
            self.messages.append(fields)

    def arrivals(self, key: str) -> list[float]:
        """When each message carrying ``key`` arrived."""
        return [t for t, m in zip(list(self.times), list(self.messages), strict=False) if key in m]

    def wait_for(self, key: str, timeout: float) -> dict[str, str]:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            for m in list(self.messages):
                if key in m:
                    return m
            time.sleep(0.05)
        raise AssertionError(f"no {key} from the daemon within {timeout} s; got {self.messages}")

    def count(self, key: str) -> int:
        return sum(1 for m in list(self.messages) if key in m)

    def close(self) -> None:
        self._stop = True
        self.sock.close()
        self._thread.join(timeout=2)


_counter = itertools.count()


class DaemonProcess:
    """``canical serve`` as a child process with a notify socket and a watchdog, as systemd runs it."""

    def __init__(self, config: Path, *, watchdog_usec: int = 1_000_000, ready_timeout: float = 90.0,
                 extra_args: tuple[str, ...] = (), extra_env: dict[str, str] | None = None) -> None:
        self.notify = NotifyListener()
        self.log_path = config.with_suffix(".daemon.log")
        env = dict(os.environ, NOTIFY_SOCKET=self.notify.name, WATCHDOG_USEC=str(watchdog_usec),
                   PYTHONUNBUFFERED="1", **(extra_env or {}))
        env.pop("WATCHDOG_PID", None)
        self._log = open(self.log_path, "w")  # noqa: SIM115 - closed in stop()
        self.started = time.monotonic()
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "canical", "serve", "--config", str(config), *extra_args],
            stdout=self._log, stderr=subprocess.STDOUT, env=env, cwd=ROOT)
        try:
            self.ready = self.notify.wait_for("READY", ready_timeout)
        except AssertionError:
            self.stop()
            raise AssertionError(f"daemon never became READY; log:\n{self.log()}") from None

    def log(self) -> str:
        return self.log_path.read_text() if self.log_path.exists() else ""

    def signal(self, sig: int) -> None:
        self.proc.send_signal(sig)

    def stop(self, timeout: float = 30.0) -> int:
        """SIGTERM and wait; the exit status."""
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
        try:
            code = self.proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            self.proc.kill()
            code = self.proc.wait()
        self._log.close()
        self.notify.close()
        return code


#: Every standard and every extended frame (a mask of 0 compares no id bit).
EVERY_FRAME = (FrameMatch(0, False, 0), FrameMatch(0, True, 0))


class Recorder:
    """Receives every frame on a channel in a thread (big kernel buffer), keeps it in order.

    On canical's own raw socket (:class:`canical.bus.raw_bus.RawSocketBus`, as ``canical record``
    reads): its socket is canical's, so the buffer is asked for through it, not through python-can's
    non-public ``bus.socket``. Error frames come too; CAN FD frames do not (nothing canical sends is one).
    """

    def __init__(self, channel: str) -> None:
        self.bus = RawSocketBus(channel, EVERY_FRAME)
        enlarge_socket_buffer(self.bus.socket, 8 << 20)  # root in the guest: room for bursts
        self.messages: list = []
        self.errors = 0
        self._stop = False
        self._thread = threading.Thread(target=self._run, daemon=True)
        self._thread.start()

    def _run(self) -> None:
        import can

        while not self._stop:
            try:
                msg = self.bus.recv(0.1)
            except can.CanError:
                self.errors += 1  # the interface went down under us; the socket stays bound
                time.sleep(0.05)
                continue
            if msg is not None:
                self.messages.append(msg)

    def of(self, frame_id: int) -> list:
        return [m for m in list(self.messages) if m.arbitration_id == frame_id and not m.is_error_frame]

    def wait_count(self, frame_id: int, n: int, timeout: float) -> list:
        end = time.monotonic() + timeout
        while time.monotonic() < end:
            got = self.of(frame_id)
            if len(got) >= n:
                return got
            time.sleep(0.05)
        return self.of(frame_id)

    def close(self) -> None:
        self._stop = True
        self._thread.join(timeout=2)
        self.bus.shutdown()



def send_paced(bus, frames: list[tuple[int, bytes]], rate_hz: float) -> None:
    """Send frames at about ``rate_hz`` (in small bursts, so sleeping stays cheap)."""
    import can

    start = time.monotonic()
    for i, (fid, data) in enumerate(frames):
        bus.send(can.Message(arbitration_id=fid, data=data, is_extended_id=False), timeout=1.0)
        if i % 8 == 7:
            lag = start + (i + 1) / rate_hz - time.monotonic()
            if lag > 0:
                time.sleep(lag)
