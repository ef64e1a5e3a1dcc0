"""Honest held-out figures: only plateaus that were held out count, and the set's headline is the
written set's own."""

import numpy as np
import pytest

from canical.calibration.pipeline import CalibrateOptions, calibrate
from canical.closed_loop.search import plateau_folds, rms
from canical.sim import effects as fx
from canical.sim import environment as env
from canical.sim.gyro import GyroModel
from canical.sim.sessions import paper_rates, sweep_session


@pytest.fixture(scope="module")
def result():
    rates = np.random.default_rng(5).permutation(np.repeat(paper_rates(), 2))
    gyro = GyroModel(effects=(fx.TemperatureEffect(bias_dps_per_c=0.01),))
    session = sweep_session(gyro, rates, dwell_s=8.0, seed=5, aux={"temp_c": env.temperature_steps()})
    return calibrate(session, CalibrateOptions(), sensor_id="S", axis="z")


def test_extreme_rates_have_no_held_out_error(result):
    """The extreme rates train every fold: no held-out error there (NaN), not a perfect one (0)."""
    loop = result.loop
    held = np.any(plateau_folds(loop.blocks), axis=0)
    rate = loop.blocks.points.rate
    assert not held.all()
    assert np.all(np.minimum(rate[~held] - rate.min(), rate.max() - rate[~held]) < 0.01 * np.ptp(rate))
    for errors in (loop.errors_before, loop.errors_after):
        assert np.isnan(errors[~held]).all() and np.isfinite(errors[held]).all()
    assert loop.rms_after == pytest.approx(float(np.sqrt(np.mean(loop.errors_after[held] ** 2))))
    # Zeros at the extremes would have made the figure better than the held-out plateaus show.
    with_zeros = float(np.sqrt(np.sum(loop.errors_after[held] ** 2) / held.size))
    assert with_zeros < loop.rms_after
    assert rms(np.array([np.nan, 3.0, 4.0])) == pytest.approx(np.sqrt(12.5))


def test_report_says_how_extremes_are_judged(result):
    section = result.report.closed_loop
    assert "extreme rates train every fold" in section.method
    extreme = section.extreme_rates_in_sample_rms_dps
    assert extreme is not None and 0.0 < extreme < 10 * section.held_out_rms_after_dps
    from canical.report.markdown import render

    assert "in sample:" in render(result.report, [])


def test_set_headline_is_the_written_sets(result):
    """fit.held_out_rms_dps is the written set's figure (rate model and effects); the rate model
    alone keeps its own figure under its own name."""
    fit = result.coefficients.fit
    section = result.report.closed_loop
    assert result.coefficients.terms
    assert fit["held_out_rms_dps"] == section.held_out_rms_after_dps
    assert fit["held_out_max_dps"] == section.held_out_max_after_dps
    assert fit["rate_model_held_out_rms_dps"] == result.report.held_out.rms_dps
    assert fit["held_out_rms_dps"] < section.held_out_rms_before_dps
