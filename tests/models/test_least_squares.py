"""The normal equations give what SVD gives, on designs like the closed loop's and on ill ones."""

from __future__ import annotations

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from canical.models.least_squares import MAX_CONDITION, NormalEquations
from canical.models.segmented_inverse import JoinedDesign, fit_segmented_inverse


def least_squares(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    return NormalEquations.of(x, y).solve()


def svd_solution(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """SVD's answer on the columns scaled to unit length (unscaled, columns 1e12 apart in size
    would cost SVD itself digits)."""
    norms = np.linalg.norm(x, axis=0)
    norms[norms == 0] = 1.0
    return np.linalg.lstsq(x / norms, y, rcond=None)[0] / norms


@settings(max_examples=60, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), rows=st.integers(30, 400), cols=st.integers(1, 12),
       scales=st.integers(0, 6))
def test_predictions_match_svd_on_columns_of_any_scale(seed: int, rows: int, cols: int, scales: int) -> None:
    """Columns of sizes 1e-6 to 1e6 apart (an effect's column beside powers of ΔV): the fitted
    values agree with SVD's to 1e-9 of the data's size."""
    rng = np.random.default_rng(seed)
    x = rng.normal(size=(rows, cols)) * 10.0 ** rng.uniform(-scales, scales, cols)
    y = rng.normal(size=rows) * 300.0
    assert np.allclose(x @ least_squares(x, y), x @ svd_solution(x, y), rtol=0, atol=1e-9 * np.abs(y).max())


def test_bordered_is_the_stacked_problem() -> None:
    rng = np.random.default_rng(1)
    x, extra, y = rng.normal(size=(200, 6)), rng.normal(size=(200, 2)), rng.normal(size=200)
    stacked = NormalEquations.of(np.hstack([x, extra]), y)
    bordered = NormalEquations.of(x, y).bordered(extra)
    assert np.allclose(bordered.gram, stacked.gram) and np.allclose(bordered.rhs, stacked.rhs)
    assert np.allclose(bordered.solve(), svd_solution(np.hstack([x, extra]), y))


def test_dependent_and_zero_columns_get_the_minimum_norm_solution() -> None:
    """Where the normal equations are singular (a zero column: a gate above every rate; two equal
    columns), the answer is SVD's minimum-norm one, not a failure or a blow-up."""
    rng = np.random.default_rng(2)
    x = rng.normal(size=(100, 3))
    y = rng.normal(size=100)
    for bad in (np.zeros((100, 1)), x[:, :1].copy(), x[:, :1] * (1 + 1e-12)):
        design = np.hstack([x, bad])
        assert np.allclose(least_squares(design, y), svd_solution(design, y))


def test_the_condition_bound_decides_the_route() -> None:
    """Just inside the bound the normal equations answer; beyond it SVD does (same answers)."""
    rng = np.random.default_rng(3)
    q, _ = np.linalg.qr(rng.normal(size=(300, 2)))
    y = rng.normal(size=300)
    for condition in (MAX_CONDITION / 10, MAX_CONDITION * 10):
        x = q @ np.diag([1.0, 1.0 / condition])
        x = x @ np.array([[1.0, 1.0], [0.0, 1.0]]) / np.sqrt(2)
        assert np.allclose(x @ least_squares(x, y), x @ svd_solution(x, y), atol=1e-9)


def test_a_joined_design_fits_as_the_one_shot_fit_does() -> None:
    """One design, several extra columns tried on it (a time constant's search): each fit is the
    fit made from scratch."""
    rng = np.random.default_rng(4)
    dv = np.sort(rng.uniform(-20000.0, 20000.0, 500))
    rate = dv / 60.0 + 1e-9 * dv**2 + rng.normal(0, 0.01, dv.size)
    weight = rng.uniform(1.0, 3.0, dv.size)
    knots = np.array([-5000.0, 5000.0])
    args = dict(scale=20000.0, span=(-20000.0, 20000.0), smoothness=0)
    joined = JoinedDesign.of(dv, rate, weight, knots, 3, **args)
    for tau in (1.0, 10.0, 100.0):
        extra = np.exp(-np.arange(dv.size) / tau)[:, None]
        once = fit_segmented_inverse(dv, rate, weight, knots, 3, extra=extra, **args)
        again = joined.fit(extra)
        assert np.allclose(again.poly.evaluate(dv)[0], once.poly.evaluate(dv)[0], atol=1e-9)
        assert np.allclose(again.extra, once.extra)
