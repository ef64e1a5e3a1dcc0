"""Properties over many simulated sensors: continuity at segment points, monotonicity."""

import numpy as np
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from canical.calibration.pipeline import CalibrateOptions, fit_base
from canical.sim.gyro import GyroModel
from canical.sim.sessions import sweep_session

sensors = st.builds(
    GyroModel,
    sensitivity=st.floats(50.0, 800.0),
    bias_counts=st.floats(-500.0, 500.0),
    asymmetry=st.floats(-0.04, 0.04),
    asymmetry_width_dps=st.floats(2.0, 15.0),
    quadratic=st.floats(-0.02, 0.02),
    cubic=st.floats(-0.04, 0.04),
    noise_dps=st.floats(0.01, 0.2),
)
RATES = np.linspace(-60, 60, 25)
settings_ = settings(max_examples=15, deadline=None, suppress_health_check=[HealthCheck.too_slow])


def sensor_is_monotone(gyro: GyroModel) -> bool:
    d = np.diff(gyro.transfer(np.linspace(-60, 60, 4001)))
    return bool(np.all(d > 0))


@settings_
@given(sensors, st.integers(0, 2**31 - 1))
def test_c0_model_does_not_jump_at_segment_points(gyro, seed):
    session = sweep_session(gyro, RATES, dwell_s=4.0, seed=seed)
    model = fit_base(session, CalibrateOptions()).fitted.model
    lo, hi = model.span
    eps = 1e-6 * (hi - lo)
    for knot in model.knots:
        below, above = model.evaluate(np.array([knot - eps, knot + eps]))[0]
        slope = abs(model.evaluate(np.array([hi]))[0][0] - model.evaluate(np.array([lo]))[0][0]) / (hi - lo)
        assert abs(above - below) <= 4 * eps * slope + 1e-9


@settings_
@given(sensors, st.integers(0, 2**31 - 1))
def test_monotone_sensor_gives_monotone_calibration(gyro, seed):
    if not sensor_is_monotone(gyro):
        return
    session = sweep_session(gyro, RATES, dwell_s=4.0, seed=seed)
    model = fit_base(session, CalibrateOptions()).fitted.model
    lo, hi = model.span
    rate = model.evaluate(np.linspace(lo - 0.1 * (hi - lo), hi + 0.1 * (hi - lo), 5000))[0]
    assert np.all(np.diff(rate) > 0)
