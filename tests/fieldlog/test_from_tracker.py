"""Field records from the tracker's events: one per standstill decision and per power-on, in time
order, the power-on count continuing from the log's origin."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import numpy as np

from canical.fieldlog.from_tracker import Origin, records
from canical.fieldlog.record import ADOPTED, POWER_ON
from canical.tracking.config import TrackerConfig
from canical.tracking.replay import replay

START = datetime(2026, 11, 27, tzinfo=UTC)


def still_drive(seed: int = 0) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Two power-ons of 40 s standing still at 100 Hz, turn-on biases 0.2 and -0.1 deg/s."""
    rng = np.random.default_rng(seed)
    t = np.arange(0, 40, 0.01)
    time_s = np.concatenate([t, t])
    noise = 0.005 * rng.standard_normal(time_s.size)
    rate = np.concatenate([np.full(t.size, 0.2), np.full(t.size, -0.1)]) + noise
    return time_s, rate, np.full(time_s.size, 30.0)


def test_a_drive_gives_a_power_on_record_then_its_standstills_for_each_power_on() -> None:
    time_s, rate, temp = still_drive()
    out = replay(time_s, rate, TrackerConfig(arw_deg_rt_h=0.3), temp_c=temp)
    got = records(out.events, out.power_ons, Origin("v1", "S1", 0xABC, 5), ("z",),
                  lambda cycle, t: START + timedelta(seconds=100 * cycle + t))
    assert [(r.decision, r.power_on) for r in got] == [(POWER_ON, 5), (ADOPTED, 5),
                                                       (POWER_ON, 6), (ADOPTED, 6)]
    assert abs(got[1].bias_dps[0] - 0.2) < 0.01 and abs(got[3].bias_dps[0] + 0.1) < 0.01
    assert got[1].temp_c == 30.0 and got[3].utc == START + timedelta(seconds=100 + got[3].since_power_on_s)


def test_a_reload_is_not_a_power_on_and_no_temperature_is_none() -> None:
    time_s, rate, _ = still_drive()
    out = replay(time_s[:4000], rate[:4000], TrackerConfig(arw_deg_rt_h=0.3))
    got = records(out.events, out.power_ons, Origin("v1", "S1", 1, 0), ("z",), lambda c, t: START,
                  temperature=False, with_first=False)
    assert [r.decision for r in got] == [ADOPTED] and got[0].temp_c is None
