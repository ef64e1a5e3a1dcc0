"""The first-order smoothing behind the lag and slope filters, against scipy's lfilter."""

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from canical.sets.trackers import _even_step, one_pole


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


def _median_rule(dt: np.ndarray) -> float | None:
    """The rule the lag's even path had before its spread check: the median, checked against all."""
    step = float(np.median(dt))
    return step if step > 0 and np.all(np.abs(dt - step) <= 1e-6 * step) else None


@settings(max_examples=200, deadline=None)
@given(st.integers(0, 2**32 - 1), st.sampled_from([0.0, 1e-9, 4e-7, 9e-7, 1.1e-6, 3e-6, 1e-3]),
       st.floats(-1e-3, 10.0), st.integers(1, 50))
def test_the_even_steps_spread_check_decides_as_the_median_did(seed, jitter, step, n):
    """:func:`_even_step` answers as the median's rule on steps even, jittered around the
    millionth, negative or zero: the spread check only skips the median where it must fail."""
    rng = np.random.default_rng(seed)
    dt = step * (1.0 + rng.uniform(-jitter, jitter, n))
    assert _even_step(dt) == _median_rule(dt)
