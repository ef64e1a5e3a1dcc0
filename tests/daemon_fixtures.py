"""Shared by the daemon tests and benchmarks: coefficient sets, configurations and IMU streams.

The configuration is always ``services/canical-can0.yaml`` (the deployable example) with its
``/etc/canical/`` paths pointed at a test folder and the channel replaced, so the example
is loaded by every daemon test and cannot rot.
"""

from __future__ import annotations

import dataclasses
import shutil
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml

from canical import coefficient_file
from canical.calibration import CalibrateOptions, calibrate
from canical.coefficients import CoefficientSet
from canical.frame_codec import load_dbc
from canical.sim.gyro import GyroModel
from canical.sim.sessions import paper_session

ROOT = Path(__file__).resolve().parents[1]
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


def write_sets(folder: Path, *, variant: int = 0) -> dict[str, Path]:
    """imu-x/y/z.yaml with the TERMS; ``variant`` shifts V0 so a second generation differs."""
    paths = {}
    base = base_set("z")
    for axis in AXES:
        cset = dataclasses.replace(base, axis=axis, terms=TERMS[axis], v0=base.v0 + 5.0 * variant)
        paths[axis] = folder / f"imu-{axis}.yaml"
        coefficient_file.save(paths[axis], cset)
    return paths


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
