"""Field records from the bias tracker's events: one per standstill decision and per power-on.

Why here and not in the tracker: the tracker knows time since power-on only; a record also
needs the wall clock, the vehicle, the sensor, the set and a power-on count that runs on across
daemon restarts and reloads. The daemon and ``apply --track-bias`` both make their records here,
so the two write the same records from the same events.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from datetime import datetime, timedelta

from canical.fieldlog.record import POWER_ON, FieldRecord
from canical.tracking.events import PowerOnEvent, StandstillEvent

#: When a record happened: (power cycle of the tracker, time since that power-on) → UTC.
Clock = Callable[[int, float], datetime]


@dataclass(frozen=True)
class Origin:
    """Where records come from: the vehicle, the sensor, the sets, and the power-on count of the
    tracker's power cycle 0 (a log continues its count: a restart is a new power-on)."""

    vehicle_id: str
    sensor_id: str
    set_id: int
    first_power_on: int


def standstill_record(event: StandstillEvent, origin: Origin, axes: tuple[str, ...], when: Clock, *,
                      temperature: bool) -> FieldRecord:
    """An adopted or refused standstill; ``temperature`` False: none was recorded (None in the record)."""
    return FieldRecord(utc=when(event.power_cycle, event.end_s), vehicle_id=origin.vehicle_id,
                       sensor_id=origin.sensor_id, set_id=origin.set_id,
                       power_on=origin.first_power_on + event.power_cycle, since_power_on_s=event.end_s,
                       temp_c=event.temp_c if temperature else None, axes=axes, bias_dps=event.mean_dps,
                       sigma_dps=event.uncertainty_dps, decision=event.decision, reason=event.reason)


def power_on_record(event: PowerOnEvent, origin: Origin, axes: tuple[str, ...], when: Clock) -> FieldRecord:
    """A power-on: the bias the tracker starts from (at its reference temperature) and its 1σ."""
    return FieldRecord(utc=when(event.power_cycle, 0.0), vehicle_id=origin.vehicle_id,
                       sensor_id=origin.sensor_id, set_id=origin.set_id,
                       power_on=origin.first_power_on + event.power_cycle, since_power_on_s=0.0,
                       temp_c=None, axes=axes, bias_dps=event.bias_dps, sigma_dps=event.sigma_dps,
                       decision=POWER_ON, reason="power-on: the turn-on bias is new")


def records(standstills: Sequence[StandstillEvent], power_ons: Sequence[PowerOnEvent], origin: Origin,
            axes: tuple[str, ...], when: Clock, *, temperature: bool = True,
            with_first: bool = True) -> list[FieldRecord]:
    """The records of a batch of events in time order (a power-on before its cycle's standstills);
    ``with_first`` False: the tracker's own start is not a power-on (a reload of the sets)."""
    starts = [power_on_record(e, origin, axes, when) for e in power_ons if with_first or e.power_cycle > 0]
    stops = [standstill_record(e, origin, axes, when, temperature=temperature) for e in standstills]
    ordered = sorted([(r.power_on, 0, r.since_power_on_s, i, r) for i, r in enumerate(starts)]
                     + [(r.power_on, 1, r.since_power_on_s, i, r) for i, r in enumerate(stops)],
                     key=lambda k: k[:4])
    return [k[4] for k in ordered]


def drive_clock(power_ons: Sequence[PowerOnEvent], start: datetime) -> Clock:
    """A recorded drive's clock: it began at ``start`` and its power-ons followed each other (each
    power-on's time since power-on runs from where the one before ended)."""
    offsets = {0: 0.0}
    elapsed = 0.0
    for event in sorted(power_ons, key=lambda e: e.power_cycle):
        if event.power_cycle > 0:
            elapsed += event.previous_end_s if event.previous_end_s == event.previous_end_s else 0.0
            offsets[event.power_cycle] = elapsed

    def when(power_cycle: int, t_s: float) -> datetime:
        return start + timedelta(seconds=offsets.get(power_cycle, elapsed) + t_s)

    return when


def drive_seconds(power_ons: Sequence[PowerOnEvent], end_s: float) -> float:
    """How long a recorded drive lasted: its power-ons' spans and the last one's ``end_s``."""
    spans = [e.previous_end_s for e in power_ons
             if e.power_cycle > 0 and e.previous_end_s == e.previous_end_s]
    return sum(spans) + (end_s if end_s == end_s else 0.0)
