"""Sizes fitted together (segment points chosen once for the most segments) are the sizes fitted
one by one: the shared choice is a saving, never a different model."""

from dataclasses import replace

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st

from canical.calibrate.cross_validation import cross_validate, cross_validate_sizes
from canical.calibrate.fit_points import FitPoints
from canical.calibrate.model_fit import ModelSpec, fit_model, fit_sizes
from canical.calibrate.model_selection import Candidate, evaluate_sizes, is_monotone
from canical.calibrate.segment_points import choose_knots, knot_sequence, knots_of
from canical.errors import CanicalError
from canical.models import RateModel

SEGMENTS = (1, 2, 3, 4, 5, 6)


def _sensor_points(seed: int, n_rates: int, bend: float, sweeps: int) -> FitPoints:
    """Plateau means of a sensor whose scale factor bends (a sine and a cubic), noisy."""
    rng = np.random.default_rng(seed)
    rate = np.tile(np.linspace(-100.0, 100.0, n_rates), sweeps)
    x = rate / 100.0
    dv = 400.0 * rate * (1.0 + bend * (0.02 * x**2 + 0.01 * np.sin(3.0 * x)))
    sem = np.full(rate.size, 0.5)
    return FitPoints(rate, dv + sem * rng.standard_normal(rate.size), np.full(rate.size, 1000.0), sem)


def _one_by_one(points: FitPoints, spec: ModelSpec) -> Candidate | None:
    """The candidate as a size on its own is judged: cross-validated, then fitted to every point."""
    try:
        held = cross_validate(points, lambda p: fit_model(p, spec).model)
        full = fit_model(points, spec)
    except (CanicalError, np.linalg.LinAlgError):
        return None
    if full.spec.n_segments != spec.n_segments:
        return None
    return Candidate(spec, held, spec.n_segments * (spec.order + 1), is_monotone(full.model, full.model.span))


point_sets = st.builds(_sensor_points, st.integers(0, 10_000), st.integers(5, 41),
                       st.floats(0.0, 30.0), st.integers(1, 2))


@settings(max_examples=25, deadline=None)
@given(point_sets, st.integers(1, 3))
def test_fewer_segments_take_the_first_points_of_the_most(points, order):
    for n in SEGMENTS:
        knots, extrema = choose_knots(points, n, min_points=order + 1)
        chosen = knot_sequence(points, max(SEGMENTS), min_points=order + 1)[: n - 1]
        np.testing.assert_array_equal(knots, knots_of(chosen))
        assert extrema == sorted(chosen, key=lambda e: e.dv)


@settings(max_examples=25, deadline=None)
@given(point_sets, st.integers(1, 3))
def test_sizes_fitted_together_are_the_sizes_fitted_alone(points, order):
    specs = [ModelSpec(n_segments=n, order=order) for n in SEGMENTS]
    for spec, together in zip(specs, fit_sizes(points, specs), strict=True):
        try:
            alone = fit_model(points, spec)
        except (CanicalError, np.linalg.LinAlgError):
            assert together is None
            continue
        assert together is not None
        assert together.spec == alone.spec and together.extrema == alone.extrema
        at = points.dv
        np.testing.assert_array_equal(together.model.evaluate(at)[0], alone.model.evaluate(at)[0])


@settings(max_examples=15, deadline=None)
@given(point_sets, st.integers(1, 3))
def test_sizes_judged_together_are_judged_as_alone(points, order):
    specs = [replace(ModelSpec(), n_segments=n, order=order) for n in SEGMENTS]
    together = evaluate_sizes(points, specs)
    for spec, got in zip(specs, together, strict=True):
        want = _one_by_one(points, spec)
        assert (got is None) == (want is None)
        if got is not None and want is not None:
            assert got.held_out.rms_dps == want.held_out.rms_dps
            assert got.held_out.fold_rms_dps == want.held_out.fold_rms_dps
            assert got.monotone == want.monotone


def test_a_size_no_fold_can_fit_is_none_and_the_others_are_judged():
    points = _sensor_points(1, 21, 10.0, 1)

    class Line:
        def __init__(self, p: FitPoints) -> None:
            self.coef = np.polyfit(p.dv, p.rate, 1)

        def evaluate(self, dv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
            return np.polyval(self.coef, dv), np.zeros(dv.size, dtype=bool)

    def fits(p: FitPoints) -> list[RateModel | None]:
        return [Line(p), None]

    line, failed = cross_validate_sizes(points, fits)
    assert failed is None
    assert line is not None and line.errors.size == np.count_nonzero(np.abs(points.rate) < 100.0)
    assert len(line.fold_rms_dps) == 5


def test_merged_points_are_kept():
    points = _sensor_points(2, 11, 0.0, 2)
    assert points.by_rate() is points.by_rate()
    assert len(points.by_rate()) == 11
