"""The closed loop's vectorised lag equals the run time's per-sample tracker, whatever the time stamps."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from canical.sets.trackers import ChannelTracker, _step_pole, lag_filter, varying_pole


def tracker_lag(values: np.ndarray, time_s: np.ndarray, tau_s: float) -> np.ndarray:
    tracker = ChannelTracker(tau_s)
    return np.array([tracker.update(v, t) for v, t in zip(values.tolist(), time_s.tolist(), strict=True)])


@settings(max_examples=60, deadline=None)
@given(
    seed=st.integers(0, 2**32 - 1),
    n=st.integers(2, 3000),
    jitter=st.sampled_from([0.0, 1e-4, 0.01, 0.5]),
    decimals=st.sampled_from([3, 4, 6, 9]),
    tau_s=st.floats(1e-3, 50.0),
    gaps=st.integers(0, 3),
    repeats=st.integers(0, 5),
)
def test_lag_filter_is_the_tracker(seed, n, jitter, decimals, tau_s, gaps, repeats):
    """Even, jittered, rounded (time stamps that repeat) and gapped records: equal within rounding."""
    rng = np.random.default_rng(seed)
    dt = 1e-2 * (1.0 + jitter * rng.uniform(-1.0, 1.0, n))
    dt[rng.integers(0, n, gaps)] *= rng.uniform(10.0, 1e5, gaps)  # a pause in the recording
    dt[rng.integers(0, n, repeats)] = 0.0  # a time stamp repeated
    time_s = np.round(100.0 + np.cumsum(dt), decimals)
    values = 25.0 + 10.0 * np.sin(time_s / rng.uniform(0.5, 50.0)) + rng.standard_normal(n)
    got = lag_filter(values, time_s, tau_s)
    want = tracker_lag(values, time_s, tau_s)
    assert np.allclose(got, want, rtol=0.0, atol=1e-9 * (1.0 + np.max(np.abs(values))))


def test_lag_filter_goes_back_to_the_tracker_when_time_runs_back():
    """A time stamp that falls back into the first τ puts the tracker back into its mean: the
    vectorised form cannot do that, so it takes the tracker's path."""
    time_s = np.array([0.0, 1.0, 2.0, 3.0, 0.5, 4.0, 5.0])
    values = np.array([1.0, 2.0, 4.0, 8.0, 16.0, 32.0, 64.0])
    assert np.array_equal(lag_filter(values, time_s, 2.5), tracker_lag(values, time_s, 2.5))


@settings(max_examples=40, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), n=st.integers(0, 2000), decay=st.floats(1e-9, 50.0))
def test_varying_pole_is_its_recursion(seed, n, decay):
    """Rows solved by a scaled cumulative sum, rows across a long gap stepped: the recursion's values."""
    rng = np.random.default_rng(seed)
    b = rng.standard_normal(n)
    log_keep = -decay * rng.random(n)
    assert np.allclose(varying_pole(b, log_keep, 3.0), _step_pole(b, log_keep, 3.0), rtol=1e-10, atol=1e-10)
