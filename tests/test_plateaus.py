"""Plateau detection: transitions and settling are left out, repeated sweeps stay separate."""

import numpy as np

from canical.plateaus import detect_plateaus, plateau_means
from canical.sim.rate_table import step_profile


def test_plateaus_found_at_each_rate_with_transitions_excluded():
    rates = np.array([0.0, 10.0, -20.0, 5.0])
    t, w = step_profile(rates, dwell_s=5.0, fs_hz=100.0, accel_dps2=50.0)
    p = detect_plateaus(t, w)
    assert p.count == 4
    np.testing.assert_allclose(p.rate_dps, rates)
    # No used sample is on a ramp, and each plateau drops its settling start.
    used = p.label >= 0
    assert np.all(np.isin(w[used], rates))
    assert p.n_transition > 0 and p.n_settling > 0
    assert p.n_used + p.n_transition + p.n_settling == len(t)
    for a in p.start:
        assert w[a - 1] == w[a]  # settling samples before the first used one are on the plateau


def test_repeated_sweeps_give_separate_plateaus():
    rates = np.array([0.0, 10.0, 0.0, 10.0])
    t, w = step_profile(rates, dwell_s=3.0, fs_hz=100.0)
    p = detect_plateaus(t, w)
    assert p.count == 4
    assert len(set(p.start)) == 4


def test_short_runs_are_not_plateaus():
    t = np.arange(300) / 100.0
    w = np.concatenate([np.zeros(200), np.full(50, 5.0), np.zeros(50)])
    p = detect_plateaus(t, w, min_duration_s=1.0)
    np.testing.assert_allclose(p.rate_dps, [0.0])


def test_noisy_reference_within_tolerance_is_one_plateau():
    rng = np.random.default_rng(0)
    t = np.arange(1000) / 100.0
    w = 30.0 + 0.005 * rng.standard_normal(1000)
    p = detect_plateaus(t, w, rate_tol=0.05)
    assert p.count == 1
    assert abs(p.rate_dps[0] - 30.0) < 0.01


def test_plateau_means_match_numpy():
    t, w = step_profile(np.array([0.0, 7.0]), dwell_s=4.0, fs_hz=50.0)
    p = detect_plateaus(t, w)
    values = np.sin(t)
    expected = [values[a:b].mean() for a, b in zip(p.start, p.stop, strict=True)]
    np.testing.assert_allclose(plateau_means(values, p), expected)
