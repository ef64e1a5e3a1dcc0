"""The three models against a known sensor, and run-time evaluation paths."""

import numpy as np
import pytest

from canical.calibrate.fit_points import FitPoints
from canical.calibrate.model_fit import ModelSpec, fit_model
from canical.calibration.pipeline import CalibrateOptions, fit_base
from canical.models.forward_poly import fit_forward_poly
from canical.models.piecewise import PiecewisePoly
from canical.models.segmented_inverse import fit_segmented_inverse
from canical.sim.gyro import GyroModel
from canical.sim.sessions import paper_session


def noiseless_points(gyro: GyroModel, rates: np.ndarray) -> FitPoints:
    dv = gyro.transfer(rates)
    return FitPoints(rates, dv, np.ones_like(rates), np.full_like(rates, 1e-3))


RATES = np.linspace(-60, 60, 41)


def test_forward_poly_inverse_recovers_rate_exactly_for_polynomial_sensor():
    gyro = GyroModel(asymmetry=0.0, ripple=0.0)  # transfer is then an exact cubic
    pts = noiseless_points(gyro, RATES)
    model = fit_forward_poly(pts.rate, pts.dv, pts.weight, 3)
    rate, oos = model.evaluate(gyro.transfer(np.array([-44.4, 0.3, 17.7])))
    np.testing.assert_allclose(rate, [-44.4, 0.3, 17.7], atol=1e-7)
    assert not oos.any()
    for w in (-44.4, 0.3, 17.7):
        one, flag = model.evaluate_one(float(gyro.transfer(np.array([w]))[0]))
        assert one == pytest.approx(w, abs=1e-7) and not flag


def test_segmented_inverse_exact_on_piecewise_polynomial_data():
    knots = np.array([-100.0, 250.0])
    true = PiecewisePoly(knots, np.array([[1.0, 60.0, 2.0], [1.0, 60.0, 3.0], [2.0, 55.0, -1.0]]), 500.0,
                         (-600.0, 600.0))
    dv = np.linspace(-600, 600, 61)
    rate = true.evaluate(dv)[0]
    fit = fit_segmented_inverse(dv, rate, np.ones_like(dv), knots, 2, scale=500.0, span=(-600.0, 600.0),
                                smoothness=None)
    np.testing.assert_allclose(fit.poly.coeffs, true.coeffs, atol=1e-9)


@pytest.mark.parametrize("smoothness", [0, 1])
def test_joined_fit_is_continuous(smoothness):
    pts = noiseless_points(GyroModel(), RATES)
    fitted = fit_model(pts, ModelSpec(n_segments=4, order=2, smoothness=smoothness))
    assert fitted.spec.n_segments == 4
    assert np.max(np.abs(fitted.model.jumps())) < 1e-9
    if smoothness == 1:
        k = fitted.model.knots
        eps = 1e-6
        left = (fitted.model.evaluate(k)[0] - fitted.model.evaluate(k - eps)[0]) / eps
        right = (fitted.model.evaluate(k + eps)[0] - fitted.model.evaluate(k)[0]) / eps
        np.testing.assert_allclose(left, right, rtol=1e-4)


def test_free_segments_jump_at_segment_points():
    session = paper_session()
    base = fit_base(session, CalibrateOptions(segments=4, order=2, smoothness=None))
    assert np.max(np.abs(base.fitted.model.jumps())) > 1e-4


def test_out_of_span_is_linear_and_flagged():
    pts = noiseless_points(GyroModel(), RATES)
    fitted = fit_model(pts, ModelSpec(n_segments=3, order=3))
    model = fitted.model
    lo, hi = model.span
    inside, oos_in = model.evaluate(np.array([lo, hi]))
    far = np.array([hi + 1000.0, hi + 2000.0, lo - 1000.0])
    out, oos_out = model.evaluate(far)
    assert not oos_in.any() and oos_out.all()
    # linear beyond the edge: equal steps in ΔV give equal steps in rate
    assert (out[1] - out[0]) == pytest.approx(out[0] - inside[1], rel=1e-9)
    assert model.evaluate_one(hi + 1000.0) == (pytest.approx(out[0]), True)


def test_scalar_and_vector_paths_agree():
    base = fit_base(paper_session(), CalibrateOptions())
    model = base.fitted.model
    dv = np.linspace(model.span[0] - 500, model.span[1] + 500, 301)
    vec, vflags = model.evaluate(dv)
    for x, r, f in zip(dv, vec, vflags, strict=True):
        one, flag = model.evaluate_one(float(x))
        assert one == pytest.approx(r, abs=1e-9) and flag == f


@pytest.mark.parametrize("order", [0, 1, 3, 5])
def test_design_matrix_is_numpys_vandermonde_in_each_segment_bit_for_bit(order):
    """The design writes u**k into the point's segment, multiplied as numpy.vander does, so every
    fit (and every set's CRC) is what the vander-based construction gave."""
    from canical.models.segmented_inverse import design

    rng = np.random.default_rng(order)
    dv, knots, scale = rng.normal(0.0, 3e4, 500), np.sort(rng.normal(0.0, 2e4, 4)), 4.1e4
    width = order + 1
    expected = np.zeros((dv.size, (knots.size + 1) * width))
    seg = np.searchsorted(knots, dv, side="right")
    cols = seg[:, None] * width + np.arange(width)
    np.put_along_axis(expected, cols, np.vander(dv / scale, width, increasing=True), axis=1)
    assert np.array_equal(design(dv, knots, order, scale), expected)
