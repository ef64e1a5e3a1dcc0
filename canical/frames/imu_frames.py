"""The IMU's frames on the bus, encoded and decoded through the DBC, for any node id.

The DBC describes the IMU at CANopen node 0x10 (IMU_RAW at 0x190 = TPDO1, IMU_AUX
at 0x290 = TPDO2, IMU_RATE at 0x390 = TPDO3). Another node id moves those frames by
the difference, the CANopen way; the byte layout always comes from the DBC. The
rate table's TABLE_REF is not an IMU frame and keeps its id.

Session columns recorded from these frames: ``time_s`` (IMU_AUX Uptime, the
device's own clock), ``temp_c`` (IMU_RAW Temperature), ``supply_v`` (IMU_AUX
SupplyVoltage), and ``ref_dps`` (TABLE_REF TableRate); the same names are the
inputs a coefficient set's effect terms are fed at run time.
"""

from __future__ import annotations

import os
import zlib
from collections.abc import Sequence
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import Any

import cantools
from cantools.database.can import Database

from canical.errors import CanicalError
from canical.frames.imu_dictionary import AXES, imu_objects

#: IMU messages in TPDO order (TPDO1, TPDO2, TPDO3).
TPDO_MESSAGES = ("IMU_RAW", "IMU_AUX", "IMU_RATE")
TABLE_MESSAGE = "TABLE_REF"
#: DBC signal → session column / run-time input name.
CHANNELS = {"Temperature": "temp_c", "SupplyVoltage": "supply_v", "Uptime": "time_s"}
#: The set tag's mask: SetTag is 4 bits wide in every frame that carries it (IMU_RATE,
#: CANICAL_RATE, CANICAL_STATUS page 1), the low bits of the combined set id.
SET_TAG_MASK = 0xF


def default_dbc_path() -> Path:
    """The DBC shipped with the package (a link to ``dbc/canical.dbc`` in the source tree)."""
    return Path(str(resources.files("canical") / "data" / "canical.dbc"))


def load_database(path: str | os.PathLike[str] | None = None) -> Database:
    name = str(path or default_dbc_path())
    if not Path(name).is_file():
        raise CanicalError(f"{name}: DBC file not found")
    try:
        return cantools.database.load_file(name, database_format="dbc")  # type: ignore[return-value]
    except Exception as exc:  # cantools raises many types for a bad file
        raise CanicalError(f"{name}: not a valid DBC file ({str(exc).splitlines()[0]})") from None


def set_tag(active_ids: dict[str, int]) -> int:
    """Low 4 bits of the combined set id, as the daemon computes it (:func:`canical.bus.active_sets.build`):
    CRC32 over the three set ids, x, y, z, each big-endian UNSIGNED32 (0 = none)."""
    blob = b"".join(int(active_ids.get(a, 0)).to_bytes(4, "big") for a in AXES)
    return zlib.crc32(blob) & SET_TAG_MASK


@dataclass(frozen=True)
class Decoded:
    name: str
    values: dict[str, Any]


class ImuFrames:
    """Encoders and a decoder for one IMU node's frames (and the table's reference)."""

    def __init__(self, node_id: int, dbc_path: str | os.PathLike[str] | None = None) -> None:
        if not 1 <= node_id <= 127:
            raise CanicalError(f"node id {node_id} outside the CANopen range 1..127")
        db = load_database(dbc_path)
        self.node_id = node_id
        self.messages = {}
        self.ids: dict[str, int] = {}
        bases = imu_objects().tpdo_cob_ids
        for name, base in zip(TPDO_MESSAGES, bases, strict=True):
            msg = db.get_message_by_name(name)
            dbc_node = msg.frame_id - base
            self.messages[name] = msg
            self.ids[name] = msg.frame_id - dbc_node + node_id
        table = db.get_message_by_name(TABLE_MESSAGE)
        self.messages[TABLE_MESSAGE] = table
        self.ids[TABLE_MESSAGE] = table.frame_id
        self._by_id = {fid: self.messages[name] for name, fid in self.ids.items()}
        #: Per message, each signal's mask: rolling counters wrap at their DBC width.
        self._masks = {name: {s.name: (1 << s.length) - 1 for s in msg.signals}
                       for name, msg in self.messages.items()}

    def encode(self, name: str, values: dict[str, float | int]) -> tuple[int, bytes]:
        """(arbitration id, payload) of one frame; values outside a signal's range are clamped."""
        msg = self.messages[name]
        return self.ids[name], msg.encode(values, scaling=True, strict=False)

    def raw(
        self, counts: tuple[int, int, int], temp_c: float, counter: int, fault: bool = False
    ) -> tuple[int, bytes]:
        x, y, z = (max(-32768, min(32767, int(c))) for c in counts)
        temp = max(-50.0, min(154.7, temp_c))
        return self.encode(
            "IMU_RAW",
            {"GyroRawX": x, "GyroRawY": y, "GyroRawZ": z, "Temperature": temp,
             "Counter": counter & self._masks["IMU_RAW"]["Counter"], "SensorFault": int(fault)},
        )

    def aux(self, supply_v: float, uptime_s: float, counter: int) -> tuple[int, bytes]:
        return self.encode(
            "IMU_AUX",
            {"SupplyVoltage": max(0.0, supply_v), "Uptime": max(0.0, uptime_s) % 4294967.0,
             "AuxCounter": counter & self._masks["IMU_AUX"]["AuxCounter"]},
        )

    def table(self, rate_dps: float, axis: str, settled: bool, counter: int) -> tuple[int, bytes]:
        """The table's frame; ``axis`` ``-x``... when the IMU's axis points against the table's."""
        return self.encode(
            TABLE_MESSAGE,
            {"TableRate": rate_dps, "TableAxis": AXES.index(axis.lstrip("-")), "TableSettled": int(settled),
             "TableAxisInverted": int(axis.startswith("-")),
             "TableCounter": counter & self._masks[TABLE_MESSAGE]["TableCounter"]},
        )

    def rate(
        self,
        rates: Sequence[float],
        out_of_span: Sequence[bool],
        uncalibrated: Sequence[bool],
        tag: int,
        counter: int,
    ) -> tuple[int, bytes]:
        masks = self._masks["IMU_RATE"]
        values: dict[str, float | int] = {"SetTag": tag & masks["SetTag"],
                                          "Counter": counter & masks["Counter"]}
        for axis, r, o, u in zip(AXES, rates, out_of_span, uncalibrated, strict=True):
            a = axis.upper()
            values[f"Rate{a}"] = max(-327.68, min(327.67, r))
            values[f"OutOfSpan{a}"] = int(o)
            values[f"Uncalibrated{a}"] = int(u)
        return self.encode("IMU_RATE", values)

    def decode(self, arbitration_id: int, data: bytes | bytearray) -> Decoded | None:
        """The frame's message name and physical values, or None for a frame of no interest."""
        msg = self._by_id.get(arbitration_id)
        if msg is None or len(data) < msg.length:
            return None
        return Decoded(msg.name, msg.decode(bytes(data), decode_choices=False))  # type: ignore[arg-type]
