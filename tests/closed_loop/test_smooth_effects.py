"""Smooth effects of a channel (issue 21): the loop learns them as splines where the enumerated
forms fall short, comes within 2x of a model told the true form on every seed, and adds nothing
on clean sensors whose channels range as widely."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import numpy as np
import pytest

from canical.calibration.evaluation import score_scenario
from canical.calibration.pipeline import CalibrateOptions, calibrate
from canical.closed_loop.candidates import (
    CHANNEL_RATE_SPLINE,
    CHANNEL_SPLINE,
    build_candidates,
    feature,
    rate_smooth_terms,
    smooth_terms,
    transform_smooth_terms,
)
from canical.report.plots import variable_label, variable_of, write_plots
from canical.sets.corrector import Corrector
from canical.sets.term_kinds import CHANNEL_DERIVATIVE_SPLINE, CHANNEL_LAG_SPLINE, spline_values
from canical.sets.terms import lag_filter
from canical.sim import environment as env
from canical.sim.gyro import GyroModel
from canical.sim.scenarios import DISTRACTORS, SMOOTH_SCENARIOS, _spline_of
from canical.sim.sessions import paper_rates, sweep_session

SEEDS = range(5)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("scenario", SMOOTH_SCENARIOS, ids=[s.name.split(":")[0] for s in SMOOTH_SCENARIOS])
def test_smooth_effect_within_twice_a_told_model(scenario, seed: int) -> None:
    r = score_scenario(scenario, seed=seed, dwell_s=8.0)
    channel = next(iter(scenario.aux))
    assert scenario.attributed(r.found)
    assert all(channel in name for name in r.found)  # the distractors are never blamed
    assert not r.confounded
    assert r.rms_after < r.rms_before / 5
    assert r.rms_after <= 2.0 * r.rms_oracle


def test_smooth_basis_sums_to_one_less_the_first_and_needs_enough_levels() -> None:
    levels = np.random.default_rng(0).uniform(0.0, 10.0, 60)
    terms = smooth_terms("load", levels)
    assert len(terms) >= 4
    assert all(t.spec is CHANNEL_SPLINE and t.params.knots == terms[0].params.knots for t in terms)
    v = np.linspace(levels.min(), levels.max(), 501)
    total = sum(t.spec.values(t, {"load": v}, v, None) for t in terms)
    assert total[0] == pytest.approx(0.0, abs=1e-12)  # the first basis function (1 at the start) left out
    assert total[-1] == pytest.approx(1.0)
    assert smooth_terms("temp_c", np.repeat([10.0, 20.0, 30.0, 40.0, 50.0], 8)) == ()  # five steps: no spline
    assert smooth_terms("flat", np.full(20, 3.0)) == ()


CLEAN_SEEDS = range(24)


@pytest.mark.parametrize("seed", CLEAN_SEEDS)
def test_clean_sensor_with_wide_ranging_channels_gets_no_smooth_effect(seed: int) -> None:
    """False alarms over 24 seeds: 0 of 24 sessions (each with two wide-ranging per-plateau
    channels and two distractors, so four smooth candidates) may add any channel effect."""
    aux = {"vib_g": env.level_per_plateau(0.5, 8.0), "load": env.level_per_plateau(0.0, 8.0), **DISTRACTORS}
    rates = np.random.default_rng(seed).permutation(np.repeat(paper_rates(), 2))
    session = sweep_session(GyroModel(), rates, dwell_s=6.0, seed=seed, aux=aux)
    result = calibrate(session, CalibrateOptions(), sensor_id="S", axis="z")
    assert result.loop is not None
    assert sum(c.name.startswith("smooth(") for c in result.loop.candidates) >= 2  # they were tried
    assert [e.name for e in result.report.effects if e.kind == "channel"] == []
    assert not any(t.kind == "channel" for t in result.coefficients.terms)


def test_learned_set_corrects_sample_by_sample_as_in_blocks_and_is_drawn(tmp_path: Path) -> None:
    scenario = SMOOTH_SCENARIOS[1]
    session = scenario.session(seed=2, dwell_s=8.0)
    result = calibrate(session, CalibrateOptions(), sensor_id="S", axis="z")
    assert result.loop is not None
    # the report draws the learned shape against the channel itself, not a basis function of it
    x, label = variable_of("smooth(load)", result.loop.blocks, result.loop)
    assert label == "load (units of load)" and np.array_equal(x, result.loop.blocks.aux["load"])
    assert variable_label("smooth(vib_g)") == "vib_g (g)"
    written = write_plots(result.loop, tmp_path)
    assert any("smooth_load" in p.name and p.stat().st_size > 0 for p in written)
    splines = [t for t in result.coefficients.terms if t.feature == "spline"]
    assert len(splines) == 1, "the saturating effect is learned as a spline, written as one term"
    assert_sample_by_sample_as_in_blocks(result, session, "load")


def test_build_candidates_offers_no_smooth_form_for_a_stepped_channel() -> None:
    scenario = next(s for s in SMOOTH_SCENARIOS if "vib_g" in s.aux)
    session = scenario.session(seed=0, dwell_s=8.0)
    result = calibrate(session, CalibrateOptions(), sensor_id="S", axis="z")
    assert result.loop is not None
    names = [c.name for c in build_candidates(result.loop.blocks, float(session.time_s[-1]))]
    assert "smooth(vib_g)" in names


def test_rate_basis_times_the_channel_sums_to_its_level() -> None:
    dv = np.linspace(-20_000.0, 20_000.0, 41)
    terms = rate_smooth_terms("temp_c", 25.0, dv)
    assert len(terms) >= 5 and all(t.spec is CHANNEL_RATE_SPLINE and t.reference == 25.0 for t in terms)
    v = np.full(dv.size, 35.0)
    total = sum(t.spec.values(t, {"temp_c": v}, dv, dv) for t in terms)
    assert np.allclose(total, 10.0)  # all basis functions: together, the channel's plain level
    assert rate_smooth_terms("temp_c", 25.0, np.repeat([-1.0, 0.0, 1.0], 5)) == ()  # three rates: none


def test_rate_coefficient_written_as_one_term_corrects_sample_by_sample_and_is_drawn(tmp_path: Path) -> None:
    """On the first of the seeds where the loop takes the smooth form (its nested hinge, as right,
    may win a draw: the scenario's told-model test holds either way)."""
    scenario = next(s for s in SMOOTH_SCENARIOS if "smooth(temp_c × rate)" in s.expect)
    for seed in SEEDS:
        session = scenario.session(seed=seed, dwell_s=8.0)
        result = calibrate(session, CalibrateOptions(), sensor_id="S", axis="z")
        assert result.loop is not None
        if "smooth(temp_c × rate)" in [e.name for e in result.loop.effects]:
            break
    else:
        pytest.fail(f"the loop took the smooth form on none of seeds {list(SEEDS)}")
    by_rate = [t for t in result.coefficients.terms if t.feature == "rate_spline"]
    assert len(by_rate) == 1, "the learned coefficient in rate is written as one term"
    written = write_plots(result.loop, tmp_path)
    assert any("smooth_temp_c_rate" in p.name and p.stat().st_size > 0 for p in written)
    assert_sample_by_sample_as_in_blocks(result, session, "temp_c")


def assert_sample_by_sample_as_in_blocks(result, session, channel: str, n: int = 3000) -> None:
    """The written set corrects the session's first ``n`` samples one at a time exactly as in a block."""
    corrector = Corrector(result.coefficients)
    inputs = {channel: session.aux[channel][:n], "time_s": session.time_s[:n]}
    block, _ = corrector.correct(session.raw[:n], inputs)
    one = [corrector.correct_one(session.raw[i], {k: float(v[i]) for k, v in inputs.items()})[0]
           for i in range(n)]
    assert np.array_equal(block, np.array(one))


def test_transform_basis_leaves_the_middle_out_with_even_knots() -> None:
    levels = np.random.default_rng(3).choice(np.linspace(-10.0, 50.0, 10), 60) + np.linspace(0.0, 0.5, 60)
    terms = transform_smooth_terms(CHANNEL_LAG_SPLINE, "temp_c", levels, 40.0, even=True)
    assert terms and all(t.spec is CHANNEL_LAG_SPLINE and t.params.tau_s == 40.0 for t in terms)
    knots = np.asarray(terms[0].params.knots)
    assert np.allclose(np.diff(knots), np.diff(knots)[0])  # evenly spaced over the levels' span
    v = np.linspace(knots[0], knots[-1], 401)
    total = sum(spline_values(t.params.knots, t.params.pieces, v) for t in terms)
    # all basis functions but the middle one: one at both ends, less than one in the middle
    assert total[0] == pytest.approx(1.0) and total[-1] == pytest.approx(1.0)
    assert total[200] < 0.9


@pytest.mark.parametrize("derivative", [False, True])
def test_block_feature_of_a_transform_spline_is_close_to_the_block_mean_of_it(derivative: bool) -> None:
    """The loop takes S of the block's mean lag (on the coarse lag) or rate, not the block mean
    of S per sample: on a lagged-temperature session the two differ by far less than S's range."""
    scenario = next(s for s in SMOOTH_SCENARIOS if "smooth(lag(temp_c))" in s.expect)
    session = scenario.session(seed=0, dwell_s=8.0)
    result = calibrate(session, CalibrateOptions(extend=True), sensor_id="S", axis="z")
    assert result.loop is not None
    blocks = result.loop.blocks
    spec = CHANNEL_DERIVATIVE_SPLINE if derivative else CHANNEL_LAG_SPLINE
    levels = np.array([-0.05, 0.05]) if derivative else np.array([-10.0, 50.0])
    fn = (lambda x: np.tanh(x / 0.02)) if derivative else scenario.effects[0].shape
    term = replace(_spline_of(fn, *levels, "temp_c", spec=spec, tau_s=15.0 if derivative else 90.0),
                   coefficient=1.0)
    at_blocks = feature(term, blocks)
    inputs = {"temp_c": session.aux["temp_c"], "time_s": session.time_s}
    per_sample = spec.values(term, inputs, session.raw, None)
    assert blocks.samples is not None
    exact = blocks.samples.means(per_sample)
    assert np.max(np.abs(at_blocks - exact)) < 0.02 * np.ptp(exact)
    assert np.ptp(exact) > 0.5  # S moves over the session: the comparison has something to see


def test_lagged_saturation_written_as_one_term_corrects_sample_by_sample_and_is_drawn(tmp_path: Path) -> None:
    scenario = next(s for s in SMOOTH_SCENARIOS if "smooth(lag(temp_c))" in s.expect)
    session = scenario.session(seed=1, dwell_s=8.0)
    result = calibrate(session, CalibrateOptions(), sensor_id="S", axis="z")
    assert result.loop is not None and [e.name for e in result.loop.effects] == ["smooth(lag(temp_c))"]
    assert result.loop.effects[0].description.startswith("smooth(lag(temp_c, τ=")
    written = [t for t in result.coefficients.terms if t.feature == "lag_spline"]
    assert len(written) == 1, "the learned shape of the lag is written as one term"
    assert 60.0 < written[0].params.tau_s < 130.0  # the die's τ is 90 s
    term = written[0]
    inputs = {"temp_c": session.aux["temp_c"], "time_s": session.time_s}
    lag = lag_filter(session.aux["temp_c"], session.time_s, term.params.tau_s)
    # x is S of the lag, sample by sample: S through the lag a lag term computes
    np.testing.assert_allclose(term.spec.values(term, inputs, session.raw, None),
                               spline_values(term.params.knots, term.params.pieces, lag), rtol=0, atol=1e-9)
    x, label = variable_of("smooth(lag(temp_c))", result.loop.blocks, result.loop)
    assert label == "lag(temp_c) (°C)"
    # drawn against the lag with the τ the fit found
    assert result.loop.blocks.samples is not None
    np.testing.assert_allclose(x, result.loop.blocks.samples.lag_means("temp_c", term.params.tau_s))
    assert any("smooth_lag" in p.name and p.stat().st_size > 0 for p in write_plots(result.loop, tmp_path))
    assert_sample_by_sample_as_in_blocks(result, session, "temp_c")


def test_saturating_transient_written_as_one_derivative_spline_corrects_sample_by_sample() -> None:
    scenario = next(s for s in SMOOTH_SCENARIOS if "smooth(d/dt temp_c)" in s.expect)
    session = scenario.session(seed=0, dwell_s=8.0)
    result = calibrate(session, CalibrateOptions(), sensor_id="S", axis="z")
    assert result.loop is not None and "smooth(d/dt temp_c)" in [e.name for e in result.loop.effects]
    written = [t for t in result.coefficients.terms if t.feature == "derivative_spline"]
    assert len(written) == 1, "the learned shape of the rate of change is written as one term"
    term = written[0]
    inputs = {"temp_c": session.aux["temp_c"], "time_s": session.time_s}
    values = session.aux["temp_c"]
    rate = (values - lag_filter(values, session.time_s, term.params.tau_s)) / term.params.tau_s
    np.testing.assert_allclose(term.spec.values(term, inputs, session.raw, None),
                               spline_values(term.params.knots, term.params.pieces, rate), rtol=0, atol=1e-9)
    assert_sample_by_sample_as_in_blocks(result, session, "temp_c")
