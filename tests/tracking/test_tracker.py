"""The bias tracker's core on small synthetic streams: stops, turns, cue, slew, power-on, temperature."""

from __future__ import annotations

import math

import numpy as np
import pytest

from canical.tracking.config import TrackerConfig
from canical.tracking.events import ADOPTED, REFUSED
from canical.tracking.replay import replay
from canical.tracking.tracker import BiasTracker

FS = 100.0
NOISE = 0.05  # deg/s per sample
CONFIG = TrackerConfig(arw_deg_rt_h=NOISE / math.sqrt(FS) * 60.0)


def stream(seconds: float, rate: float, seed: int = 0, t0: float = 0.0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    t = t0 + np.arange(int(seconds * FS)) / FS
    return t, rate + NOISE * rng.standard_normal(t.size)


def test_a_stop_is_learned_with_its_uncertainty() -> None:
    t, r = stream(20, 0.35)
    out = replay(t, r, CONFIG, temp_c=np.full(t.size, 25.0))
    (event,) = out.events
    assert event.decision == ADOPTED
    assert abs(event.mean_dps[0] - 0.35) < 4 * event.uncertainty_dps[0]
    assert event.uncertainty_dps[0] < 0.005
    assert abs(out.bias_dps[-1, 0] - 0.35) < 0.01
    assert out.learned[0].updates == event.windows_used


@pytest.mark.parametrize(("rate", "seconds"), [(15.0, 40), (95.0, 2.5), (95.0, 40)])
def test_a_steady_turn_is_never_a_bias_nor_listed_as_a_standstill(rate: float, seconds: float) -> None:
    """Only candidate standstills (a low rate) are events: a steady turn, long or short, is driving."""
    t, r = stream(seconds, rate)
    for cue in (None, np.zeros(t.size)):
        cfg = TrackerConfig(arw_deg_rt_h=CONFIG.arw_deg_rt_h, cue_threshold=None if cue is None else 0.5)
        out = replay(t, r, cfg, cue=cue)
        assert out.taken == () and out.events == ()
        assert np.all(out.bias_dps == 0.0)


def test_a_run_a_little_past_the_bound_is_a_refused_standstill() -> None:
    t, r = stream(40, 1.5)
    out = replay(t, r, CONFIG)
    assert out.taken == ()
    assert [e.decision for e in out.events] == [REFUSED]
    assert "plausibility bound" in out.events[0].reason


def test_with_a_cue_nothing_is_learned_while_it_says_moving() -> None:
    t, r = stream(20, 0.2)
    cfg = TrackerConfig(arw_deg_rt_h=CONFIG.arw_deg_rt_h, cue_threshold=0.5)
    out = replay(t, r, cfg, cue=np.full(t.size, 3.0))
    assert out.taken == ()
    assert "cue says moving" in out.events[0].reason
    missing = replay(t, r, cfg, cue=np.full(t.size, np.nan))  # no cue value counts as moving
    assert missing.taken == ()
    stopped = replay(t, r, cfg, cue=np.zeros(t.size))
    assert stopped.events[0].decision == ADOPTED


def test_a_signed_speed_in_reverse_is_moving() -> None:
    """A cue that goes negative (a vehicle speed signed by direction) says moving by its size."""
    t, r = stream(20, 0.2)
    cfg = TrackerConfig(arw_deg_rt_h=CONFIG.arw_deg_rt_h, cue_threshold=0.5)
    reversing = replay(t, r, cfg, cue=np.full(t.size, -3.0))
    assert reversing.taken == ()
    assert "cue says moving" in reversing.events[0].reason
    creeping_back = replay(t, r, cfg, cue=np.full(t.size, -0.2))  # within ± the threshold: stands
    assert creeping_back.events[0].decision == ADOPTED


def test_the_applied_bias_slews_without_a_step() -> None:
    t, r = stream(30, 0.6)
    out = replay(t, r, CONFIG)
    steps = np.abs(np.diff(out.bias_dps[:, 0]))
    assert steps.max() <= CONFIG.slew_dps_per_s / FS * (1 + 1e-9)
    assert abs(out.bias_dps[-1, 0] - 0.6) < 0.01


def test_a_power_on_relearns_a_new_turn_on_bias() -> None:
    t1, r1 = stream(20, 0.35, seed=1)
    t2, r2 = stream(20, -0.2, seed=2)  # time since power-on starts again
    out = replay(np.r_[t1, t2], np.r_[r1, r2], CONFIG)
    assert out.power_cycles == 2
    assert [e.power_cycle for e in out.events] == [0, 1]
    assert abs(out.bias_dps[-1, 0] + 0.2) < 0.01


def test_the_temperature_slope_carries_the_bias_between_stops() -> None:
    """Stops at 20, 30 and 40 °C with 0.012 deg/s/°C: the bias at 45 °C is predicted, not measured."""
    times, rates, temps = [], [], []
    t0 = 0.0
    for k, temp in enumerate((20.0, 30.0, 40.0)):
        t, r = stream(20, 0.3 + 0.012 * (temp - 20.0), seed=k, t0=t0)
        times += [t, t[-1] + 0.01 + np.arange(2000) / FS]
        rates += [r, 5.0 * np.sin(np.arange(2000) / FS)]  # driving between stops
        temps += [np.full(t.size, temp), np.linspace(temp, temp + 10.0, 2000)]
        t0 = times[-1][-1] + 0.01
    out = replay(np.concatenate(times), np.concatenate(rates), CONFIG, temp_c=np.concatenate(temps))
    learned = out.learned[0]
    assert learned.slope == pytest.approx(0.012, abs=0.002)
    assert learned.at(45.0, CONFIG.reference_c) == pytest.approx(0.6, abs=0.02)


def test_step_and_replay_are_bit_for_bit_the_same() -> None:
    t, r = stream(30, 0.4)
    temp = np.linspace(20, 30, t.size)
    out = replay(t, r, CONFIG, temp_c=temp)
    tracker = BiasTracker(("z",), CONFIG)
    by_step = np.array([tracker.step(ti, [ri], te)[0] for ti, ri, te in
                        zip(t.tolist(), r.tolist(), temp.tolist(), strict=True)])
    assert np.array_equal(by_step, out.bias_dps[:, 0])


def test_three_axes_share_one_standstill() -> None:
    t, _ = stream(20, 0.0)
    rng = np.random.default_rng(3)
    rates = np.array([0.1, -0.2, 0.3]) + NOISE * rng.standard_normal((t.size, 3))
    out = replay(t, rates, CONFIG, axes=("x", "y", "z"))
    assert out.bias_dps[-1] == pytest.approx([0.1, -0.2, 0.3], abs=0.01)
    assert "y -0.20" in out.events[0].line(("x", "y", "z"))


@pytest.mark.parametrize("bad", [{"window_s": 0.0}, {"bound_dps": -1.0}, {"min_run_windows": 0},
                                 {"cue_threshold": math.nan}, {"cue_threshold": 0.0},
                                 {"arw_deg_rt_h": math.inf}])
def test_bad_settings_are_refused(bad: dict[str, float]) -> None:
    with pytest.raises(ValueError):
        TrackerConfig(**bad)


def test_time_jitter_backwards_is_not_a_power_on() -> None:
    t, r = stream(20, 0.3)
    t = t.copy()
    t[800] = t[799] - 0.02  # a timestamp out of order while the bias slews
    out = replay(t, r, CONFIG)
    assert out.power_cycles == 1
    steps = np.abs(np.diff(out.bias_dps[:, 0]))
    assert steps[798] > 0 and steps[799] == 0.0  # slewing; time stood still at the late stamp
    assert steps[800] <= CONFIG.slew_dps_per_s * (t[801] - t[799]) * (1 + 1e-9)
