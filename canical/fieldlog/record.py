"""One field record: what the bias tracker decided at one standstill or power-on, on one vehicle.

Why a typed, checked record: the daemon writes it, the fleet tools read it back months later on
another machine; a record that does not hold its own invariants (finite numbers, one value per
axis, a known decision) is refused when it is made and when it is read, never half-used.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

ADOPTED = "adopted"
REFUSED = "refused"
POWER_ON = "power-on"
DECISIONS = (ADOPTED, REFUSED, POWER_ON)

#: The record's fields in their order on a line (the segment's header names them).
FIELDS = ("utc", "vehicle_id", "sensor_id", "set_id", "power_on", "since_power_on_s", "temp_c",
          "axes", "bias_dps", "sigma_dps", "decision", "reason")


class RecordError(ValueError):
    """A record that breaks its invariants (the message names the field)."""


@dataclass(frozen=True)
class FieldRecord:
    """One decision of the tracker: when, where, on which sensor and set, and what it measured."""

    utc: datetime  # timezone-aware, UTC
    vehicle_id: str
    sensor_id: str
    set_id: int  # the sets' combined id (0: none known)
    power_on: int  # power-ons counted by this vehicle's log, from 0
    since_power_on_s: float
    temp_c: float | None  # None: no temperature recorded
    axes: tuple[str, ...]
    bias_dps: tuple[float, ...]  # adopted/refused: the standstill's mean; power-on: the learned bias
    sigma_dps: tuple[float, ...]  # 1σ of bias_dps
    decision: str  # ADOPTED, REFUSED or POWER_ON
    reason: str = ""

    def __post_init__(self) -> None:
        for problem in _problems(self):
            raise RecordError(problem)

    def to_json(self) -> dict[str, Any]:
        """The record as JSON values (time as ISO 8601 with microseconds and Z)."""
        return {"utc": self.utc.astimezone(UTC).strftime("%Y-%m-%dT%H:%M:%S.%fZ"),
                "vehicle_id": self.vehicle_id, "sensor_id": self.sensor_id, "set_id": self.set_id,
                "power_on": self.power_on, "since_power_on_s": self.since_power_on_s,
                "temp_c": self.temp_c, "axes": list(self.axes), "bias_dps": list(self.bias_dps),
                "sigma_dps": list(self.sigma_dps), "decision": self.decision, "reason": self.reason}

    @classmethod
    def from_json(cls, value: Any) -> FieldRecord:
        """A record from :meth:`to_json`'s values; :class:`RecordError` naming what is wrong."""
        if not isinstance(value, dict) or sorted(value) != sorted(FIELDS):
            raise RecordError(f"a record has the fields {', '.join(FIELDS)}")
        try:
            utc = datetime.strptime(value["utc"], "%Y-%m-%dT%H:%M:%S.%fZ").replace(tzinfo=UTC)
            return cls(utc=utc, vehicle_id=value["vehicle_id"], sensor_id=value["sensor_id"],
                       set_id=value["set_id"], power_on=value["power_on"],
                       since_power_on_s=_number(value["since_power_on_s"]),
                       temp_c=None if value["temp_c"] is None else _number(value["temp_c"]),
                       axes=tuple(value["axes"]), bias_dps=tuple(map(_number, value["bias_dps"])),
                       sigma_dps=tuple(map(_number, value["sigma_dps"])), decision=value["decision"],
                       reason=value["reason"])
        except (TypeError, ValueError) as exc:
            raise RecordError(f"a bad record: {exc}") from None


def _number(value: Any) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float):
        raise RecordError(f"{value!r} is not a number")
    return float(value)


def _problems(r: FieldRecord) -> list[str]:
    """What is wrong with a record, first problem first (empty: nothing)."""
    checks = [
        (isinstance(r.utc, datetime) and r.utc.tzinfo is not None, "utc must be a timezone-aware time"),
        (isinstance(r.vehicle_id, str) and bool(r.vehicle_id), "vehicle_id must be a non-empty string"),
        (isinstance(r.sensor_id, str), "sensor_id must be a string"),
        (_integer(r.set_id) and r.set_id >= 0, "set_id must be an integer ≥ 0"),
        (_integer(r.power_on) and r.power_on >= 0, "power_on must be an integer ≥ 0"),
        (_finite(r.since_power_on_s), "since_power_on_s must be finite"),
        (r.temp_c is None or _finite(r.temp_c), "temp_c must be finite or None"),
        (bool(r.axes) and all(isinstance(a, str) and a for a in r.axes), "axes must be names"),
        (len(r.bias_dps) == len(r.axes) and all(map(_finite, r.bias_dps)),
         "bias_dps must be one finite value per axis"),
        (len(r.sigma_dps) == len(r.axes) and all(_finite(s) and s >= 0 for s in r.sigma_dps),
         "sigma_dps must be one finite value ≥ 0 per axis"),
        (r.decision in DECISIONS, f"decision must be one of {', '.join(DECISIONS)}"),
        (isinstance(r.reason, str), "reason must be a string"),
    ]
    return [message for ok, message in checks if not ok]


def _integer(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _finite(value: Any) -> bool:
    return isinstance(value, int | float) and not isinstance(value, bool) and math.isfinite(value)
