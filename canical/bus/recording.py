"""Record an IMU live from the bus: one sample per IMU_RAW frame, the rest held at its latest value.

The same rule as the daemon and :mod:`canical.sessions.canlog`: each raw frame is a
sample; temperature rides in it, uptime and supply come from the latest IMU_AUX,
the table's rate from the latest TABLE_REF. The device's own corrected rates
(IMU_RATE, on-device correction) are attached to the sample whose counter they
carry, so the device's output can be compared with ``canical apply`` sample by
sample. Works for any node id (frames located through :class:`ImuFrames`).
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import can
import numpy as np

from canical.bus.raw_bus import open_receive_bus
from canical.errors import CanicalError
from canical.frames.frame_match import FrameMatch
from canical.frames.imu_dictionary import AXES
from canical.frames.imu_frames import ImuFrames
from canical.sessions.session import Session

COLUMNS = ("received_s", "time_s", "temp_c", "supply_v", "ref_dps", "table_axis", "settled", "counter",
           *(f"raw_{a}" for a in AXES), *(f"device_rate_{a}" for a in AXES), "device_tag")


@dataclass
class Recording:
    """Samples as recorded, column by column (NaN where a value was not on the bus yet)."""

    columns: dict[str, list[float]] = field(default_factory=lambda: {c: [] for c in COLUMNS})
    frames: int = 0

    def __len__(self) -> int:
        return len(self.columns["time_s"])

    def array(self, name: str) -> np.ndarray:
        return np.asarray(self.columns[name], dtype=float)

    def session(self, axis: str, sensor: str, *, reference: bool = True) -> Session:
        """One axis as a session; with ``reference`` only samples with a table rate about this axis."""
        keep = np.isfinite(self.array("time_s")) & np.isfinite(self.array("temp_c"))
        keep &= np.isfinite(self.array("supply_v"))
        ref = None
        if reference:
            keep &= np.isfinite(self.array("ref_dps")) & (self.array("table_axis") == AXES.index(axis))
        if not keep.any():
            raise CanicalError(f"no complete sample of axis {axis} recorded ({self.frames} frames seen)")
        if reference:
            ref = self.array("ref_dps")[keep]
        return Session(
            time_s=self.array("time_s")[keep],
            raw=self.array(f"raw_{axis}")[keep],
            ref_dps=ref,
            aux={"temp_c": self.array("temp_c")[keep], "supply_v": self.array("supply_v")[keep]},
            meta={"sensor": sensor, "axis": axis},
        )


def record(
    bus: can.BusABC,
    frames: ImuFrames,
    *,
    samples: int | None = None,
    duration_s: float | None = None,
    until: Callable[[Recording], bool] | None = None,
    idle_timeout_s: float = 2.0,
) -> Recording:
    """Record until ``samples`` raw frames, ``duration_s`` wall seconds, or ``until`` says so.

    Raises :class:`CanicalError` when no IMU frame arrives for ``idle_timeout_s``.
    """
    ids = frames.ids
    rec = Recording()
    cols = rec.columns
    held = {"time_s": math.nan, "supply_v": math.nan, "ref_dps": math.nan, "table_axis": math.nan,
            "settled": math.nan}
    start = time.monotonic()
    last_seen = start
    nan3 = (math.nan,) * 3
    while True:
        if samples is not None and len(rec) >= samples:
            break
        if duration_s is not None and time.monotonic() - start >= duration_s:
            break
        if until is not None and until(rec):
            break
        msg = bus.recv(timeout=0.2)
        if msg is None:
            if time.monotonic() - last_seen > idle_timeout_s:
                raise CanicalError(f"no IMU frame on the bus for {idle_timeout_s:g} s "
                                   f"(node 0x{frames.node_id:02x}, IMU_RAW id 0x{ids['IMU_RAW']:03x})")
            continue
        decoded = frames.decode(msg.arbitration_id, msg.data)
        if decoded is None or msg.is_error_frame or msg.is_remote_frame:
            continue
        last_seen = time.monotonic()
        rec.frames += 1
        v = decoded.values
        if decoded.name == "IMU_AUX":
            held["time_s"] = float(v["Uptime"])
            held["supply_v"] = float(v["SupplyVoltage"])
        elif decoded.name == "TABLE_REF":
            held["ref_dps"] = float(v["TableRate"])
            held["table_axis"] = float(v["TableAxis"])
            held["settled"] = float(v["TableSettled"])
        elif decoded.name == "IMU_RAW":
            for name, value in held.items():
                cols[name].append(value)
            cols["received_s"].append(last_seen)
            cols["temp_c"].append(float(v["Temperature"]))
            cols["counter"].append(float(v["Counter"]))
            for a, d in zip(AXES, nan3, strict=True):
                cols[f"raw_{a}"].append(float(v[f"GyroRaw{a.upper()}"]))
                cols[f"device_rate_{a}"].append(d)
            cols["device_tag"].append(math.nan)
        elif (decoded.name == "IMU_RATE" and len(rec) and cols["counter"][-1] == v["Counter"]
              and math.isnan(cols["device_tag"][-1])):
            for a in AXES:
                unc = v[f"Uncalibrated{a.upper()}"]
                cols[f"device_rate_{a}"][-1] = math.nan if unc else float(v[f"Rate{a.upper()}"])
            cols["device_tag"][-1] = float(v["SetTag"])
    return rec


def open_recorder_bus(interface: str, channel: str, frames: ImuFrames, **options: Any) -> can.BusABC:
    """A bus receiving only the IMU's frames and the table's (kernel filters where it can); on
    SocketCAN with a receive buffer of seconds of frames, so that a recorder busy decoding loses
    none meanwhile (:func:`~canical.bus.raw_bus.open_receive_bus`).

    ``options`` are the interface's own settings, passed through as python-can types them (Any).
    """
    matches = [FrameMatch(fid, False, 0x7FF) for fid in frames.ids.values()]
    try:
        return open_receive_bus(interface, channel, matches, **options)
    except Exception as exc:  # python-can raises many types
        raise CanicalError(f"cannot open CAN interface {interface} channel {channel}: {exc}") from None
