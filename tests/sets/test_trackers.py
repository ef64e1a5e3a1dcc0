"""The first-order smoothing behind the lag and slope filters, against scipy's lfilter."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from canical.sets.trackers import one_pole


def lfilter_one_pole(x: np.ndarray, a: float, before: float) -> np.ndarray:
    from scipy.signal import lfilter

    y, _ = lfilter([a], [1.0, a - 1.0], x, zi=[(1.0 - a) * before])
    return np.asarray(y)


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 3000), st.floats(1e-7, 1.0), st.floats(-1e3, 1e3), st.integers(0, 2**31))
def test_one_pole_is_lfilters_smoothing(n, a, before, seed):
    """Any length (rows of the product and a tail), any smoothing from a near-hold to none."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=n) * 10 + rng.normal() * 100
    want = lfilter_one_pole(x, a, before)
    scale = np.abs(want).max(initial=1.0) + abs(before)
    np.testing.assert_allclose(one_pole(x, a, before), want, rtol=0, atol=1e-11 * scale)


def test_one_pole_over_millions_of_samples_stays_within_rounding():
    rng = np.random.default_rng(7)
    x = rng.normal(size=2_000_000) + 5.0
    for a in (1e-5, 0.01, 0.9):
        want = lfilter_one_pole(x, a, 2.0)
        np.testing.assert_allclose(one_pole(x, a, 2.0), want, rtol=0, atol=1e-12 * np.abs(want).max())


def test_one_pole_is_finite_up_to_the_first_sample_that_is_not():
    x = np.arange(200, dtype=float)
    x[150] = np.nan
    y = one_pole(x, 0.1, 0.0)
    np.testing.assert_allclose(y[:150], lfilter_one_pole(x[:150], 0.1, 0.0), rtol=1e-13)
    assert np.isnan(y[150:]).all()
