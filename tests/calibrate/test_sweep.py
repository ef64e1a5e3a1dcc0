"""A session recorded as a slow continuous sweep: calibrated from short windows where its
reference supports that, refused with the advice to record steps where it does not; step
sessions untouched."""

from __future__ import annotations

import numpy as np
import pytest
from support.sessions import write_session

from canical.calibrate.plateaus import detect_plateaus
from canical.calibrate.sweep_windows import MAX_SPREAD_DPS, SweepCheck, sweep_check, window_length
from canical.calibration.evaluation import held_out_set_errors
from canical.calibration.pipeline import (
    CalibrateOptions,
    calibrate,
    find_plateaus,
    fit_base,
    sweep_or_plateaus,
)
from canical.commands.cli import main
from canical.sessions.session import Session
from canical.sets.coefficient_file import load
from canical.sim.gyro import GyroModel
from canical.sim.sessions import between_rates_session, paper_session
from canical.sim.sweeps import SweepProgramme, sweep_recording

#: A sensor other than the default: a sharper knee, other curvature, more noise, a slower filter.
OTHER = GyroModel(sensitivity=250.0, bias_counts=-80.0, asymmetry=0.04, asymmetry_width_dps=4.0,
                  quadratic=-0.02, cubic=0.03, noise_dps=0.12, bandwidth_hz=25.0)
#: A ripple of 0.11 deg/s every 25 deg/s, and a wide gentle knee with little noise: with segment
#: points at residual extrema the sweep got 5 and 3 segments (order 5) and 2.7x and 2.6x the step
#: session's error (sensors drawn by ``bench_sweep.py``, seeds 70017 and 70034, rounded).
RIPPLED = GyroModel(sensitivity=275.0, bias_counts=-88.0, asymmetry=0.0085, asymmetry_width_dps=6.2,
                    quadratic=-0.007, cubic=0.0475, ripple=0.0019, ripple_period_dps=25.0, noise_dps=0.066,
                    bandwidth_hz=71.0)
GENTLE = GyroModel(sensitivity=109.0, bias_counts=-85.0, asymmetry=0.0073, asymmetry_width_dps=9.6,
                   quadratic=0.02, cubic=0.043, ripple=0.0008, ripple_period_dps=33.0, noise_dps=0.052,
                   bandwidth_hz=92.5)


def _judged(session: Session, judge: Session) -> float:
    result = calibrate(session, CalibrateOptions(), sensor_id="SIM", axis="z")
    return float(np.sqrt(np.mean(held_out_set_errors(result.coefficients, judge) ** 2)))


@pytest.mark.parametrize(("gyro", "seed"), [(GyroModel(), 11), (GyroModel(), 12), (OTHER, 13), (RIPPLED, 15),
                                            (GENTLE, 15)])
def test_a_sweep_calibrates_within_the_bar_of_a_step_session(gyro: GyroModel, seed: int) -> None:
    """The same sensor, a step session and a sweep of the same length (encoder rate at 100 Hz,
    late by 10 ms), both sets judged on a third step session at the rates midway: the sweep's
    error within 1.5x the step's."""
    step = paper_session(gyro, seed=seed)
    programme = SweepProgramme(duration_s=float(step.time_s[-1] - step.time_s[0]), encoder_lsb_dps=0.02,
                               ref_latency_s=0.01)
    sweep = sweep_recording(gyro, programme, seed=seed + 100)
    judge = between_rates_session(gyro, seed=seed + 200)
    assert _judged(sweep, judge) <= 1.5 * _judged(step, judge)


def test_the_windows_follow_the_sweep() -> None:
    """Consecutive windows within the spread bound, their rates on the truth once the delay is
    fitted (the sensor's filter and the reference's hold and latency), V0 at the zero crossing."""
    gyro = GyroModel()
    sweep = sweep_recording(gyro, SweepProgramme(duration_s=400.0, ref_latency_s=0.015), seed=3)
    base = fit_base(sweep, CalibrateOptions(extend=False))
    p = base.plateaus
    assert p.sweep_window_s == pytest.approx(MAX_SPREAD_DPS / 0.6, rel=0.05)  # 240 deg/s in 400 s
    assert p.count > 300 and np.all(p.start[1:] >= p.stop[:-1])
    # sensor 4 ms behind the table (40 Hz), the reference 15 ms + half its 10 ms hold: -16 ms
    assert -p.latency_s == pytest.approx(-0.016, abs=0.002)
    assert base.v0 == pytest.approx(gyro.bias_counts, abs=0.01 * gyro.sensitivity)


def test_a_step_session_is_untouched() -> None:
    """A step session's plateaus are plateau finding's own, the very object."""
    session = paper_session(GyroModel(), seed=5)
    found = find_plateaus(session, CalibrateOptions())
    assert sweep_or_plateaus(session, found, CalibrateOptions()) is found
    assert found.sweep_window_s == 0.0


def test_a_one_way_sweep_through_an_exact_encoder_is_calibrated(tmp_path) -> None:
    """-60 to 60 deg/s once at 0.5 deg/s² (its rate held at 100 Hz, exact): a delay cannot be
    fitted from one direction, the reference's estimated latency stands in; the CLI writes a set."""
    fs = 100.0
    t = np.arange(0.0, 240.0, 1.0 / fs)
    ref = 60.0 - np.abs((0.5 * t) % 240.0 - 120.0)
    held = ref[(np.floor(t * 100.0) / 100.0 * fs).astype(int)]
    raw = np.round(GyroModel().output(t, ref, rng=np.random.default_rng(1), fs_hz=fs))
    path = write_session(tmp_path / "sweep.csv", Session(time_s=t, raw=raw, ref_dps=held,
                                                          meta={"sensor": "SIM-1", "axis": "z"}))
    assert main(["calibrate", str(path), "-o", str(tmp_path / "set.yaml")]) == 0
    assert (tmp_path / "set.yaml").exists()


def test_a_sweep_with_a_coarse_encoder_is_refused_with_the_advice(tmp_path, capsys) -> None:
    """An encoder whose rate is quantised to 0.2 deg/s changes only every 0.2 deg/s of the sweep:
    a window of ten of its values would spread over 2 deg/s; one line, exit 2, the sweep told
    apart and steps advised."""
    sweep = sweep_recording(GyroModel(), SweepProgramme(encoder_lsb_dps=0.2, ref_hz=100.0), seed=4)
    path = write_session(tmp_path / "coarse.csv", sweep)
    capsys.readouterr()
    assert main(["calibrate", str(path), "-o", str(tmp_path / "set.yaml")]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("canical calibrate: error: "), err
    assert "Traceback" not in err and not (tmp_path / "set.yaml").exists()
    assert "continuous sweep, not a noisy reference" in err
    assert "its reference too coarse or slow for it: 0.2 deg/s between updates (above 0.05)" in err
    assert "record the rates as steps" in err


def test_the_criterion_from_its_figures() -> None:
    """A 100 Hz encoder of 0.02 deg/s supports a 0.6 deg/s² sweep; of 0.5 deg/s it does not; at
    10 Hz a 2 deg/s² sweep moves 0.2 deg/s between updates, above the bound."""
    good = sweep_recording(GyroModel(), SweepProgramme(encoder_lsb_dps=0.02), seed=6)
    coarse = sweep_recording(GyroModel(), SweepProgramme(encoder_lsb_dps=0.5), seed=6)
    for session, refused in ((good, False), (coarse, True)):
        found = detect_plateaus(session.time_s, session.ref_dps, raw=session.raw)
        check = sweep_check(session.time_s, session.ref_dps, session.raw, found)
        assert bool(check.refusal()) is refused
    assert window_length(2.0, 0.1, 0.01) == pytest.approx(1.0)  # ten updates, spread 2 deg/s
    noisy = SweepCheck(window_s=1.0, moved_per_update_dps=0.01, reference_error_dps=0.02,
                       sensor_noise_dps=0.01)
    assert "too noisy for it: 0.02 deg/s on a window (the sensor's noise: 0.01)" in noisy.refusal()


def test_a_sweep_joins_its_segments_at_evenly_spaced_points(tmp_path) -> None:
    """A sweep's segment points are evenly spaced in ΔV and more than six may be chosen (the
    ripple wants them); the written set, read back, corrects as the set calibrate returned."""
    step = paper_session(RIPPLED, seed=16)
    sweep = sweep_recording(RIPPLED, SweepProgramme(duration_s=float(step.time_s[-1]), encoder_lsb_dps=0.02,
                                                    ref_latency_s=0.01), seed=116)
    result = calibrate(sweep, CalibrateOptions(), sensor_id="SIM", axis="z")
    spec = result.report.spec
    assert spec.endswith("points=even") and int(spec.split("segments=")[1].split()[0]) > 6, spec
    knots = fit_base(sweep, CalibrateOptions(extend=False)).fitted.model.knots
    assert np.allclose(np.diff(knots), np.diff(knots)[0])
    path = write_session(tmp_path / "sweep.csv", sweep)
    assert main(["calibrate", str(path), "-o", str(tmp_path / "set.yaml")]) == 0
    judge = between_rates_session(RIPPLED, seed=216)
    np.testing.assert_allclose(held_out_set_errors(load(tmp_path / "set.yaml"), judge),
                               held_out_set_errors(result.coefficients, judge), atol=1e-9)


def test_a_step_session_keeps_its_extrema() -> None:
    """A step session's segment points are still its residual's extrema (sizes up to six)."""
    spec = fit_base(paper_session(RIPPLED, seed=17), CalibrateOptions(extend=False)).fitted.spec
    assert not spec.even_points and spec.n_segments <= 6
