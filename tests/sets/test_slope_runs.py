"""The vectorised slope over a record that is evenly spaced in stretches (gaps, a short last
mean, repeated or missing timestamps) equals the per-sample tracker within rounding."""

from __future__ import annotations

import numpy as np
import pytest

from canical.sets.trackers import slope_filter, slope_state


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
def test_stretches_of_even_spacing_equal_the_tracker(seed):
    rng = np.random.default_rng(seed)
    n = 30_000
    time_s = np.arange(n) * 0.003
    for at in rng.integers(100, n - 100, 4):  # gaps: the spacing changes from there on
        time_s[at:] += rng.uniform(0.001, 2.0)
    time_s[-1] = time_s[-2] + 0.001  # the last mean is of fewer rows
    dup = int(rng.integers(1000, n - 1000))
    time_s[dup + 1] = time_s[dup]  # a repeated timestamp: the tracker skips it
    uneven = int(rng.integers(1000, n - 1000))
    time_s[uneven : uneven + 40] += rng.uniform(0, 0.001, 40).cumsum().clip(max=0.0025)
    raw = np.cumsum(rng.normal(0, 5, n)) + 200 * np.sin(time_s)
    tracker = slope_state(raw, time_s, 0.5)
    fast = slope_filter(raw, time_s, 0.5)
    assert np.isfinite(tracker).all()
    np.testing.assert_allclose(fast, tracker, rtol=1e-9, atol=1e-9 * np.abs(np.diff(raw)).max() / 0.003)


def test_nan_carried_as_the_tracker_carries_it():
    n = 5000
    time_s = np.arange(n) / 1000.0
    raw = np.sin(time_s * 7.0) * 100.0
    raw[3000] = np.nan
    fast = slope_filter(raw, time_s, 0.2)
    tracker = slope_state(raw, time_s, 0.2)
    assert np.isnan(fast[3000:]).all() and np.isnan(tracker[3000:]).all()
    np.testing.assert_allclose(fast[:3000], tracker[:3000], rtol=1e-9, atol=1e-9)
