"""A simulated fleet's field logs, drawn from the models, with the truth beside them.

Why drawn and not replayed: the fleet tools read what the trackers decided, not raw samples; a
standstill's record is the sensor's bias at that moment (its turn-on value, its temperature
slope left over by the table's, its aging) plus the tracker's measurement noise, so a fleet of
1,000 vehicles over 30 days is a few hundred thousand draws, not billions of samples. Each
vehicle has one z-axis sensor from a lot (a turn-on spread and a slope error typical of the
lot), a climate (its ambient temperatures), one to three drives a day (the cabin warming from
ambient towards 40 °C), standstills through each drive, now and then one refused. A few sensors
are planted: *aging* (the bias drifting with operating hours) and *failing* (a turn-on spread or
a temperature slope error beyond the spec). Vehicle ``k`` of seed ``s`` is the same vehicle
whatever the fleet's size.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta

import numpy as np

from canical.fieldlog.record import ADOPTED, POWER_ON, REFUSED, FieldRecord

START = datetime(2026, 10, 1, tzinfo=UTC)
LOTS = ("A24", "B25", "C25", "D26")
#: Per climate: the day's mean ambient temperature (°C) and its spread from day to day.
CLIMATES = {"cold": (-5.0, 6.0), "temperate": (12.0, 5.0), "hot": (28.0, 4.0)}
CABIN_C = 40.0  # what the cabin warms towards while driving
CABIN_TAU_S = 1200.0
REFERENCE_C = 25.0  # the tracker's reference temperature
NOISE_DPS = 0.003  # a standstill's measurement 1σ
TURN_ON_PRIOR_DPS = 0.5  # the tracker's turn-on spread (a power-on record's 1σ)
IN_SPEC, DRIFTING, OUT_OF_SPEC = "in spec", "drifting", "out of spec"
#: The share of sensors planted aging, and failing.
AGING_SHARE, FAILING_SHARE = 0.03, 0.02


@dataclass(frozen=True)
class SensorTruth:
    """What a simulated sensor really is: the truth the fleet analysis is judged against."""

    vehicle_id: str
    sensor_id: str
    lot: str
    climate: str
    verdict: str  # IN_SPEC, DRIFTING or OUT_OF_SPEC
    turn_on_mean_dps: float
    turn_on_spread_dps: float  # 1σ of the turn-on bias from power-on to power-on
    slope_dps_per_c: float  # the bias's temperature slope left over after the set's
    drift_dps_per_h: float  # the bias's drift per operating hour


def vehicle_id(index: int) -> str:
    return f"veh-{index:05d}"


def draw_sensor(index: int, rng: np.random.Generator) -> SensorTruth:
    """The vehicle's sensor: its lot's and climate's draws, planted aging or failing by chance."""
    lot = LOTS[int(rng.integers(len(LOTS)))]
    lot_k = LOTS.index(lot)
    climate = tuple(CLIMATES)[int(rng.integers(len(CLIMATES)))]
    spread = float(rng.uniform(0.05, 0.12 + 0.06 * lot_k))
    slope = float(np.clip(rng.normal(0.001 * (lot_k - 1.5), 0.002), -0.006, 0.006))
    drift, verdict = 0.0, IN_SPEC
    plant = rng.uniform()
    if plant < AGING_SHARE:
        drift, verdict = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.01, 0.03)), DRIFTING
    elif plant < AGING_SHARE + FAILING_SHARE:
        verdict = OUT_OF_SPEC
        if rng.uniform() < 0.5:
            spread = float(rng.uniform(0.7, 1.0))
        else:
            slope = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.02, 0.04))
    return SensorTruth(vehicle_id(index), f"{lot}-{index:05d}", lot, climate, verdict,
                       float(rng.normal(0.0, 0.2)), spread, slope, drift)


def simulate_vehicle(index: int, days: int, seed: int = 0) -> tuple[SensorTruth, list[FieldRecord]]:
    """One vehicle's sensor and the records its daemon would write over ``days`` days."""
    rng = np.random.default_rng([seed, index])
    truth = draw_sensor(index, rng)
    set_id = int(rng.integers(1, 2**32))
    records: list[FieldRecord] = []
    hours = 0.0
    power_on = 0
    last = 0.0
    mean_c, spread_c = CLIMATES[truth.climate]
    for day in range(days):
        ambient = mean_c + spread_c * float(rng.standard_normal()) + 8.0 * math.sin(2 * math.pi * day / 365)
        for drive in range(int(rng.integers(1, 4))):
            start = START + timedelta(days=day, hours=7 + 5 * drive + float(rng.uniform(0, 3)))
            length = float(rng.uniform(1200, 5400))
            turn_on = truth.turn_on_mean_dps + truth.turn_on_spread_dps * float(rng.standard_normal())
            base = _record(truth, set_id, start, power_on, 0.0, None, last, TURN_ON_PRIOR_DPS, POWER_ON,
                           "power-on: the turn-on bias is new")
            records.append(base)
            times = np.sort(rng.uniform(60, length, int(rng.integers(3, 10))))
            for t in times:
                temp = CABIN_C + (ambient - CABIN_C) * math.exp(-t / CABIN_TAU_S)
                bias = (turn_on + truth.slope_dps_per_c * (temp - REFERENCE_C)
                        + truth.drift_dps_per_h * (hours + t / 3600)
                        + NOISE_DPS * float(rng.standard_normal()))
                sigma = NOISE_DPS * float(rng.uniform(0.8, 1.25))
                when = start + timedelta(seconds=float(t))
                if rng.uniform() < 0.08:  # a slow turn taken for a stop: refused
                    records.append(_record(truth, set_id, when, power_on, float(t), round(temp, 2),
                                           bias + float(rng.choice([-1.0, 1.0])) * 1.5, sigma, REFUSED,
                                           "beyond the plausibility bound ±1 deg/s: a turn, not a bias"))
                    continue
                records.append(_record(truth, set_id, when, power_on, float(t), round(temp, 2), bias, sigma,
                                       ADOPTED, "still windows taken in"))
                last = bias
            hours += length / 3600
            power_on += 1
    return truth, records


def _record(truth: SensorTruth, set_id: int, when: datetime, power_on: int, t: float, temp: float | None,
            bias: float, sigma: float, decision: str, reason: str) -> FieldRecord:
    return FieldRecord(utc=when, vehicle_id=truth.vehicle_id, sensor_id=truth.sensor_id, set_id=set_id,
                       power_on=power_on, since_power_on_s=round(t, 1), temp_c=temp, axes=("z",),
                       bias_dps=(bias,), sigma_dps=(sigma,), decision=decision, reason=reason)
