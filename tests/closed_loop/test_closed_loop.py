"""The closed loop on sessions with undeclared effects: right attribution, near-told accuracy."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support.sessions import write_session

from canical.calibrate.plateaus import detect_plateaus
from canical.calibration.evaluation import score_scenario
from canical.calibration.pipeline import CalibrateOptions, calibrate
from canical.closed_loop.search import CONFOUND_ALPHA, better_p
from canical.commands.cli import main
from canical.sets import coefficient_file
from canical.sets.corrector import Corrector
from canical.sim import effects as fx
from canical.sim import environment as env
from canical.sim.gyro import GyroModel
from canical.sim.scenarios import SCENARIOS
from canical.sim.sessions import paper_rates, sweep_session


@pytest.mark.parametrize("scenario", SCENARIOS, ids=[s.name for s in SCENARIOS])
def test_scenario_attribution_and_error(scenario):
    r = score_scenario(scenario, seed=3, dwell_s=8.0)
    assert scenario.attributed(r.found), r.found
    if scenario.confounded:
        assert r.confounded, "confounded candidates must be reported"
        assert set(scenario.confounded) <= {n for g in r.confounded for n in g}
        assert r.rms_after < r.rms_before / 3  # one adopted: ambiguous, yet corrected
    elif scenario.gyro is None:
        assert not r.confounded
    else:  # coloured noise: a rate random walk *is* a drift; it may be found, a channel never
        assert all(name.startswith("time:") for name in r.found)
    if scenario.confounded and "temp_c" in scenario.aux:  # the recorded channel is named in it
        assert any("temp_c" in n for g in r.confounded for n in g)
    if scenario.expect and not scenario.leaves_residual:
        assert r.rms_after < r.rms_before / 3
        assert r.rms_after <= 1.5 * r.rms_oracle  # within a small factor of a model told the effect
    if scenario.confounded:  # the form adopted is not the true one, but corrects within 2x of it
        assert r.rms_after <= 2.0 * r.rms_oracle
    if not scenario.effects and scenario.gyro is None:
        assert r.rms_after == pytest.approx(r.rms_before)
    # What the loop could not represent is reported as unexplained (a confound is corrected).
    assert r.unexplained == scenario.leaves_residual


CONFOUNDS = [s for s in SCENARIOS if s.confounded]


@pytest.mark.parametrize("seed", (0, 1, 2))
@pytest.mark.parametrize("scenario", CONFOUNDS, ids=[s.name for s in CONFOUNDS])
def test_confounds_are_reported_on_other_seeds(scenario, seed):
    """The confound check on more sessions than seed 3: each of these once added one explanation
    outright (self-heating and the ramp at seed 1: a candidate scored on a base size its own size
    search never reached; the transient at seed 0), where the data cannot tell them apart. One is
    adopted all the same, as ambiguous (not an attribution: ``found`` stays empty), and the set
    is corrected to within 2x of a model told the true form, the residual explained."""
    r = score_scenario(scenario, seed=seed, dwell_s=8.0)
    assert r.found == ()
    twins = {n for g in r.confounded for n in g if not n.startswith("~")}
    assert set(scenario.confounded) <= twins, r.confounded
    assert any("temp_c" in n for n in twins), r.confounded
    assert r.rms_after <= 2.0 * r.rms_oracle < r.rms_before
    assert not r.unexplained
    # Each twin is within what the held-out plateaus' scatter allows of the first named.
    assert all(p >= CONFOUND_ALPHA for group in r.paired_p for p in group.values())


def test_paired_test_holds_its_level_and_sees_a_real_difference():
    """Held-out losses of two equally good explanations (squared errors: heavy-tailed, and alike on
    neighbouring plateaus) are called different about as often as the level says, not more; losses
    of an explanation with twice the error are told apart nearly always."""
    rng = np.random.default_rng(7)
    n, trials = 78, 2000

    def losses(scale):
        slow = np.convolve(rng.standard_normal(n + 3), np.ones(4) / 2.0, mode="valid")  # neighbours alike
        return (scale * (slow + rng.standard_normal(n))) ** 2

    null = [better_p(losses(1.0), losses(1.0)) < CONFOUND_ALPHA for _ in range(trials)]
    assert np.mean(null) <= 2.5 * CONFOUND_ALPHA
    power = [better_p(losses(1.0), losses(2.0)) < CONFOUND_ALPHA for _ in range(200)]
    assert np.mean(power) > 0.9


@settings(max_examples=60, deadline=None)
@given(st.lists(st.floats(0.0, 10.0), min_size=3, max_size=40), st.floats(1e-3, 5.0))
def test_paired_test_is_one_sided_and_paired(values, shift):
    """p(a better than b) and p(b better than a) are complementary, and adding the same loss to every
    plateau of b (a uniformly worse explanation, however scattered the losses) is certain."""
    a = np.asarray(values)
    b = a[::-1] + np.linspace(0.0, 1.0, a.size)
    if np.ptp(b - a) > 1e-9:
        assert better_p(a, b) + better_p(b, a) == pytest.approx(1.0)
    assert better_p(a, a + shift) < 1e-12
    assert better_p(a + shift, a) > 1 - 1e-12


@pytest.mark.parametrize("seed", range(6))
def test_noise_channels_are_never_picked(seed):
    """Clean sensors with several channels that carry only noise (white or wandering)."""
    aux = {f"white_{i}": env.white_noise(0.0, 1.0 + i) for i in range(3)}
    aux |= {f"walk_{i}": env.random_walk(0.05 * (i + 1)) for i in range(2)}
    rates = np.random.default_rng(seed).permutation(paper_rates())
    session = sweep_session(GyroModel(), rates, dwell_s=8.0, seed=seed, aux=aux)
    result = calibrate(session, CalibrateOptions(), sensor_id="S", axis="z")
    assert result.report.effects == ()
    assert result.coefficients.terms == ()


def test_prefer_resolves_a_confounded_pair():
    scenario = next(s for s in SCENARIOS if "self-heating" in s.name)
    # seed 1: the session at which the warm-up was once attributed outright (see above)
    session = scenario.session(seed=1, dwell_s=8.0)
    result = calibrate(session, CalibrateOptions(prefer=("channel:temp_c",)), sensor_id="S", axis="z")
    assert [e.name for e in result.report.effects] == ["channel:temp_c"]
    assert result.report.confounded[0].resolved_by_user == "channel:temp_c"
    assert "random order" in result.report.confounded[0].recommendation
    # The report says on what evidence: the paired test's p for each twin, all above its level.
    from canical.report.markdown import render

    group = result.report.confounded[0]
    assert set(group.paired_p) == set(group.candidates[1:])
    assert min(group.paired_p.values()) >= group.paired_alpha
    assert "paired test, one-sided, level 0.01" in render(result.report, [])


def effect_session():
    rates = np.random.default_rng(4).permutation(np.repeat(paper_rates(), 2))
    gyro = GyroModel(effects=(fx.TemperatureEffect(bias_dps_per_c=0.01, scale_per_c=2e-4),
                              fx.DirectionEffect(0.04)))
    return sweep_session(gyro, rates, dwell_s=8.0, seed=4,
                         aux={"temp_c": env.temperature_steps(), "noise_ch": env.white_noise()})


def test_extended_set_corrects_field_data_in_order(tmp_path):
    session = effect_session()
    result = calibrate(session, CalibrateOptions(), sensor_id="S", axis="z")
    kinds = {t.kind for t in result.coefficients.terms}
    assert kinds == {"channel", "direction"}
    cset = coefficient_file.loads(coefficient_file.dumps(result.coefficients))
    corrector = Corrector(cset)
    assert corrector.required_inputs == ("temp_c",)
    rate, _ = corrector.correct(session.raw, {"temp_c": session.aux["temp_c"]})
    plain, _ = Corrector(calibrate(session, CalibrateOptions(extend=False), sensor_id="S",
                                   axis="z").coefficients).correct(session.raw)
    used = detect_plateaus(session.time_s, session.ref_dps).label >= 0
    err_ext = np.sqrt(np.mean((rate - session.ref_dps)[used] ** 2))
    err_plain = np.sqrt(np.mean((plain - session.ref_dps)[used] ** 2))
    assert err_ext < err_plain / 2
    # One sample at a time (the daemon's path) gives the same numbers as the block.
    one = Corrector(cset)
    scalar = [one.correct_one(r, {"temp_c": t})[0] for r, t in zip(session.raw[:4000],
                                                                   session.aux["temp_c"][:4000], strict=True)]
    np.testing.assert_allclose(scalar, rate[:4000], atol=1e-9)


def test_cli_loop_report_dir_and_apply(tmp_path, capsys):
    path = write_session(tmp_path / "s.csv", effect_session())
    coeffs, rep = tmp_path / "c.yaml", tmp_path / "report"
    assert main(["calibrate", str(path), "-o", str(coeffs), "--report-dir", str(rep)]) == 0
    out = capsys.readouterr().out
    assert "effects    channel:temp_c, direction" in out
    names = sorted(p.name for p in rep.iterdir())
    assert "report.md" in names and "residual_vs_rate.png" in names
    assert any(n.startswith("effect_1_channel_temp_c") for n in names)
    md = (rep / "report.md").read_text()
    assert "**written set**" in md and "channel:temp_c" in md
    assert main(["apply", str(coeffs), str(path), "-o", str(tmp_path / "o.csv")]) == 0
    # Without the temperature column the set cannot be applied: one line, status 2.
    lines = path.read_text().splitlines()
    header = lines[2].split(",")
    keep = [i for i, h in enumerate(header) if h != "temp_c"]
    stripped = tmp_path / "no_temp.csv"
    stripped.write_text("\n".join(lines[:2] + [",".join(r.split(",")[i] for i in keep)
                                               for r in lines[2:]]) + "\n")
    capsys.readouterr()
    assert main(["apply", str(coeffs), str(stripped), "-o", str(tmp_path / "o2.csv")]) == 2
    assert "missing column 'temp_c'" in capsys.readouterr().err


def test_no_extend_fits_the_model_alone(tmp_path):
    path = write_session(tmp_path / "s.csv", effect_session())
    coeffs = tmp_path / "c.yaml"
    assert main(["calibrate", str(path), "-o", str(coeffs), "--no-extend"]) == 0
    assert coefficient_file.load(coeffs).terms == ()


def test_time_candidates_tied_to_the_rate_order_are_reported_not_fitted():
    """One ascending sweep: time since power-on *is* the table rate, so a time term would
    predict the reference (a leak that vanishes in the field). It must not be accepted."""
    gyro = GyroModel(effects=(fx.WarmupEffect(0.2, 200.0),))
    session = sweep_session(gyro, paper_rates(), dwell_s=2.0, fs_hz=100.0, seed=2)
    result = calibrate(session, CalibrateOptions(), sensor_id="S", axis="z")
    assert result.report.closed_loop is not None
    names = {u.candidate for u in result.report.closed_loop.untestable}
    assert {"time:warm-up", "time:linear-drift"} <= names
    assert all(e.kind != "time" for e in result.report.effects)


CLEAN_NOISE = {
    "white": GyroModel(),
    "bias instability + rate random walk": GyroModel(bias_instability_dps=0.003,
                                                     rate_random_walk_dps_rt_s=1e-4),
}


@pytest.mark.parametrize("noise", list(CLEAN_NOISE))
@pytest.mark.parametrize("seed", range(10))
def test_clean_sensors_get_nothing_blamed_on_a_channel(noise, seed):
    """With every channel transform a candidate, five channels that carry nothing (one slowly
    varying like a room's temperature) must still get nothing, also when the noise is not white."""
    scenario = next(s for s in SCENARIOS if s.name.startswith("clean, white noise, 5 distractors"))
    rates = np.random.default_rng(seed).permutation(np.repeat(paper_rates(), 2))
    session = sweep_session(CLEAN_NOISE[noise], rates, dwell_s=6.0, seed=seed, aux=scenario.aux)
    result = calibrate(session, CalibrateOptions(), sensor_id="S", axis="z")
    assert [e.name for e in result.report.effects if e.kind == "channel"] == []
    assert not any(t.kind == "channel" for t in result.coefficients.terms)
    assert result.report.unexplained is not None and not result.report.unexplained.unexplained


def test_allan_terms_switch_on_and_off():
    """Each noise term of the simulator is switchable, and each shows where an Allan plot puts it."""
    t = np.arange(1_000_000) / 200.0
    quiet = GyroModel(noise_dps=0.0, lsb=0.0)
    flat = quiet.output(t, np.zeros_like(t))
    assert np.ptp(flat) == 0.0  # all off: a constant output

    def allan(x, m):  # non-overlapping Allan deviation of the rate at cluster size m samples
        means = x[: x.size // m * m].reshape(-1, m).mean(axis=1) / 400.0
        return np.sqrt(0.5 * np.mean(np.diff(means) ** 2))

    rrw = GyroModel(noise_dps=0.0, lsb=0.0, rate_random_walk_dps_rt_s=1e-3).output(t, np.zeros_like(t))
    # Rate random walk: σ(τ) = K·√(τ/3) (within sampling scatter at τ = 50 s).
    assert allan(rrw, 10_000) == pytest.approx(1e-3 * np.sqrt(50 / 3), rel=0.3)
    bi = GyroModel(noise_dps=0.0, lsb=0.0, bias_instability_dps=0.01).output(t, np.zeros_like(t))
    # Bias instability: a flat floor ≈ 0.664·B over decades of τ.
    floor = [allan(bi, m) for m in (200, 2_000, 20_000)]  # τ = 1, 10, 100 s
    assert all(0.5 * 0.00664 < f < 1.5 * 0.00664 for f in floor), floor
    white = GyroModel(lsb=0.0).output(t, np.zeros_like(t))
    assert allan(white, 200) == pytest.approx(0.08 / np.sqrt(200), rel=0.1)  # N/√τ


def test_unexplained_residual_is_reported_plotted_and_strict_fails(tmp_path, capsys):
    """A sensor following a variable nobody recorded: the loop cannot represent it and says so."""
    from canical.sim.scenarios import UNEXPLAINED

    session = UNEXPLAINED.session(seed=2, dwell_s=8.0)
    path = write_session(tmp_path / "s.csv", session)
    rep = tmp_path / "report"
    status = main(["calibrate", str(path), "-o", str(tmp_path / "c.yaml"), "--report-dir", str(rep),
                   "--strict"])
    out = capsys.readouterr()
    assert status == 3
    assert "unexplained:" in out.out and "× the noise floor" in out.out
    assert "strict" in out.err
    import json

    left = json.loads((rep / "report.json").read_text())["unexplained"]
    assert left["unexplained"] and left["ratio"] > 3
    assert left["held_out_rms_dps"] > 3 * left["noise_floor_dps"]
    assert (rep / "unexplained_residual.png").stat().st_size > 10_000
    assert "Unexplained:" in (rep / "report.md").read_text()
    # A looser limit lets it through; a clean sensor passes --strict at the default.
    assert main(["calibrate", str(path), "-o", str(tmp_path / "c.yaml"), "--strict", "50"]) == 0
    clean = write_session(tmp_path / "clean.csv", sweep_session(
        GyroModel(), np.random.default_rng(1).permutation(paper_rates()), dwell_s=8.0, seed=1))
    capsys.readouterr()
    assert main(["calibrate", str(clean), "-o", str(tmp_path / "c2.yaml"), "--strict"]) == 0
    assert "explained" in capsys.readouterr().out
    with pytest.raises(SystemExit) as bad:  # a multiple below 1 is refused, as argparse does
        main(["calibrate", str(clean), "-o", str(tmp_path / "c2.yaml"), "--strict", "0.5"])
    assert bad.value.code == 2


def test_thermal_transient_set_corrects_sample_by_sample():
    """A set with a derivative term, applied as the daemon and the emulator do (one sample at a
    time, inputs by name), gives the block path's numbers and beats the rate model alone."""
    scenario = next(s for s in SCENARIOS if s.name.startswith("thermal transient: bias"))
    session = scenario.session(seed=5, dwell_s=8.0)
    result = calibrate(session, CalibrateOptions(), sensor_id="S", axis="z")
    assert [e.name for e in result.report.effects] == ["d/dt temp_c"]
    cset = coefficient_file.loads(coefficient_file.dumps(result.coefficients))
    inputs = {"temp_c": session.aux["temp_c"], "time_s": session.time_s}
    assert set(Corrector(cset).required_inputs) == {"temp_c", "time_s"}
    rate, _ = Corrector(cset).correct(session.raw, inputs)
    one = Corrector(cset)
    scalar = [one.correct_one(session.raw[i], {k: v[i] for k, v in inputs.items()})[0] for i in range(3000)]
    np.testing.assert_allclose(scalar, rate[:3000], atol=1e-9)
    plain, _ = Corrector(calibrate(session, CalibrateOptions(extend=False), sensor_id="S",
                                   axis="z").coefficients).correct(session.raw)
    used = detect_plateaus(session.time_s, session.ref_dps).label >= 0
    err = np.sqrt(np.mean((rate - session.ref_dps)[used] ** 2))
    assert err < np.sqrt(np.mean((plain - session.ref_dps)[used] ** 2))


def test_rate_gated_effect_is_found_with_its_knee_and_applied_sample_by_sample():
    """A temperature scale error acting only above 30 dps: the loop names the channel gated by the
    rate with the knee it estimated, and the set (no state) gives the block path's numbers one sample
    at a time, and beats the rate model alone."""
    scenario = next(s for s in SCENARIOS if s.name.startswith("temperature scale error only above"))
    session = scenario.session(seed=6, dwell_s=8.0)
    result = calibrate(session, CalibrateOptions(), sensor_id="S", axis="z")
    effects = result.report.effects
    assert [e.name for e in effects] == ["temp_c × (|rate| > knee)"]
    knee = float(effects[0].description.split("> ")[1].split(" dps")[0])
    assert 25 <= knee <= 35, effects[0].description
    assert {t.feature for t in result.coefficients.terms} == {"gated"}
    cset = coefficient_file.loads(coefficient_file.dumps(result.coefficients))
    assert Corrector(cset).required_inputs == ("temp_c",)
    temp = session.aux["temp_c"]
    rate, _ = Corrector(cset).correct(session.raw, {"temp_c": temp})
    one = Corrector(cset)
    scalar = [one.correct_one(session.raw[i], {"temp_c": temp[i]})[0] for i in range(0, len(temp), 7)]
    np.testing.assert_array_equal(scalar, rate[::7])
    plain, _ = Corrector(calibrate(session, CalibrateOptions(extend=False), sensor_id="S",
                                   axis="z").coefficients).correct(session.raw)
    label = detect_plateaus(session.time_s, session.ref_dps).label
    used = label >= 0

    def plateau_rms(r):  # the sample noise averages out over a plateau; the effect does not
        sums, counts = np.bincount(label[used], (r - session.ref_dps)[used]), np.bincount(label[used])
        return np.sqrt(np.mean((sums[counts > 0] / counts[counts > 0]) ** 2))

    assert plateau_rms(rate) < plateau_rms(plain) / 3
