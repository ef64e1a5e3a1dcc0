"""The start guard follows the settling the session shows (in the sensor's output), not a fixed rule.

A commanded reference is exact on every plateau: it cannot show the table ringing after a
rate change, nor a slow sensor filter catching up. The sensor's own output shows both; the
guard taken from it keeps ringing and filter lag out of the fit, where the old fixed rule
(0.5 s or a tenth of the plateau: 0.8 s here) used them.
"""

import json

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support.trials.table_grid import IDEAL, grid_rates

from canical.calibrate.plateaus import observed_settling_s
from canical.calibration.pipeline import CalibrateOptions, calibrate
from canical.commands.cli import main
from canical.sessions.csv_file import format_session
from canical.sim.gyro import GyroModel
from canical.sim.sessions import recorded_sweep
from canical.sim.table_recording import TableBehaviour

DWELL_S, FS_HZ = 8.0, 100.0
OLD_RULE_S = 0.1 * DWELL_S  # 0.5 s or a tenth of the plateau
#: Ringing that outlasts the old rule: 30% overshoot at 1 Hz, decaying over 0.8 s.
RINGING = TableBehaviour(accel_dps2=100.0, overshoot=0.3, ring_hz=1.0, ring_decay_s=0.8)
SLOW_FILTER = GyroModel(bandwidth_hz=0.5)  # time constant 0.32 s


def _run(table, gyro=None, seed=0, settle_s=None):
    gyro = gyro or GyroModel()
    session, rec = recorded_sweep(gyro, grid_rates(), table, dwell_s=DWELL_S, fs_hz=FS_HZ, seed=seed)
    result = calibrate(session, CalibrateOptions(extend=False, settle_s=settle_s), sensor_id="SIM", axis="z")
    return result, rec


def _ringing_rows(result, rec, noise_dps):
    """Used rows where the table's true rate is off its commanded rate by more than the sensor's noise."""
    used = result.base.plateaus.label >= 0
    off = np.abs(rec.true_dps - rec.commanded_dps)[rec.kept]
    return int(np.count_nonzero(used & (off > noise_dps)))


@pytest.mark.parametrize("seed", [0, 1])
def test_ringing_with_a_commanded_reference_is_not_used(seed):
    result, rec = _run(RINGING, seed=seed)
    found = result.report.plateau_finding
    assert found.settle_source == "observed"
    assert found.settle_s > OLD_RULE_S
    assert _ringing_rows(result, rec, GyroModel().noise_dps) == 0
    assert result.base.plateaus.count == grid_rates().size
    ideal = _run(IDEAL, seed=seed)[0].report.held_out.rms_dps
    assert result.report.held_out.rms_dps <= 1.3 * ideal
    # The old fixed rule, given as --settle, used ringing rows: the guard matters here.
    old, _ = _run(RINGING, seed=seed, settle_s=OLD_RULE_S)
    assert _ringing_rows(old, rec, GyroModel().noise_dps) > 0


def test_slow_sensor_filter_is_waited_for():
    result, rec = _run(IDEAL, gyro=SLOW_FILTER)
    p = result.base.plateaus
    tau = 1 / (2 * np.pi * SLOW_FILTER.bandwidth_hz)
    # A 3 deg/s step decays as 3·exp(-s/τ): within twice the sensor's noise after τ·ln(3/(2·0.08)).
    lag_s = tau * np.log(3.0 / (2 * SLOW_FILTER.noise_dps))
    assert result.report.plateau_finding.settle_s >= lag_s
    ticks = rec.time_s[rec.kept]
    used = p.label >= 0
    since_step = ticks[used] - rec.schedule.end[p.label[used]]
    assert since_step.min() >= lag_s
    ideal = _run(IDEAL)[0].report.held_out.rms_dps
    assert result.report.held_out.rms_dps <= 1.3 * ideal


def test_ideal_session_keeps_a_short_guard():
    result, _ = _run(IDEAL)
    found = result.report.plateau_finding
    assert found.settle_source == "observed"
    assert found.settle_s == pytest.approx(0.1)
    assert found.observed_settling_s < 0.1


@settings(max_examples=25, deadline=None)
@given(tau=st.floats(0.05, 0.6), step=st.floats(200.0, 2000.0), sigma=st.floats(5.0, 40.0),
       seed=st.integers(0, 2**16))
def test_observed_settling_brackets_an_exponential_settle(tau, step, sigma, seed):
    """Plateaus settling as step·exp(-s/τ) in white noise: never before the decay enters the band
    of a window's noise, and not long after it is well inside (noise near the band's edge can
    still poke out, which only makes the guard safer).

    Noise alone lifts one plateau's settling in about 25 (a 0.1 s window past 4 standard errors
    somewhere in 5 s); the pooled upper quartile ignores that unless a quarter of the plateaus
    are lifted: with 12 plateaus one example in 600 was (a 4 % chance per run of 25 examples),
    with 40 none in 3000."""
    rng = np.random.default_rng(seed)
    fs, dwell, n_plateaus = 100.0, 10.0, 40
    s = np.arange(int(dwell * fs)) / fs
    t = np.concatenate([k * dwell + s for k in range(n_plateaus)])
    raw = np.concatenate([1000.0 * k + step * np.exp(-s / tau) for k in range(n_plateaus)])
    raw = raw + sigma * rng.standard_normal(raw.size)
    stretches = [(k * s.size, (k + 1) * s.size) for k in range(n_plateaus)]
    got = observed_settling_s(t, raw, stretches, 1.0, 1 / fs)
    band = 4.0 * sigma / np.sqrt(10)  # 4 standard errors of a 0.1 s window mean
    reach = tau * np.log(step / band)  # where the decay itself enters the band
    assert reach - 0.15 <= got <= reach + tau * np.log(4.0) + 0.15


def test_report_says_where_the_guard_came_from(tmp_path):
    session, _ = recorded_sweep(GyroModel(), grid_rates()[::4], RINGING, dwell_s=DWELL_S, fs_hz=FS_HZ, seed=0)
    csv = tmp_path / "s.csv"
    csv.write_text(format_session(session))
    out = tmp_path / "r"
    assert main(["calibrate", str(csv), "--no-extend", "-o", str(tmp_path / "set.yaml"),
                 "--report-dir", str(out)]) == 0
    found = json.loads((out / "report.json").read_text())["plateau_finding"]
    assert found["settle_source"] == "observed"
    assert "sensor settled in" in (out / "report.md").read_text()
    assert main(["calibrate", str(csv), "--no-extend", "--settle", "1.5", "-o", str(tmp_path / "set.yaml"),
                 "--report", str(tmp_path / "g.json")]) == 0
    given_ = json.loads((tmp_path / "g.json").read_text())["plateau_finding"]
    assert given_["settle_source"] == "given" and given_["settle_s"] == 1.5
