"""A session longer than the bound is read as means of k samples; calibration on the means gives
the set the samples give, within the fit's own tolerance, and loses no rail hit."""

from __future__ import annotations

import json
from dataclasses import replace

import numpy as np
import pytest
from support.table_clock import own_clock_case, table_csv

from canical.calibrate.allan import NoiseAnalysis
from canical.calibration.pipeline import CalibrateOptions, calibrate, fit_base
from canical.commands.cli import main
from canical.errors import CanicalError
from canical.sessions import csv_chunks, row_means
from canical.sessions.csv_file import format_session, read_session, read_table, session_from_table
from canical.sessions.session import Session
from canical.sets.corrector import Corrector
from canical.sim.gyro import GyroModel
from canical.sim.sessions import paper_rates, sweep_session

SEEDS = (0, 1, 2)
#: A sensor whose converter clips at 20000 counts (50 deg/s), turned to ±60 deg/s.
CLIPPING = GyroModel(rail_counts=20000.0)


def _write(tmp_path, session: Session, name: str = "s.csv"):
    path = tmp_path / name
    path.write_text(format_session(session))
    return path


def test_means_extremes_and_settled_flags_of_k_rows(tmp_path, monkeypatch):
    monkeypatch.setattr(csv_chunks, "CHUNK_BYTES", 97)  # blocks that cut groups of k anywhere
    n = 101
    t = np.arange(n) / 10.0
    raw = (np.arange(n) * 37 % 23).astype(float)
    settled = (np.arange(n) % 7 != 3).astype(float)
    text = "# sensor: S\ntime_s,ref_dps,raw,settled,temp_c\n" + "".join(
        f"{t[i]:g},{i // 20:g},{raw[i]:g},{settled[i]:g},{20 + i:g}\n" for i in range(n))
    path = tmp_path / "s.csv"
    path.write_text(text)
    session = read_session(path, settled_column="settled", max_rows=30)  # k = 4: 25 means and one of 1
    assert session.means is not None and session.means.k == 4
    assert session.means.line() == "101 rows read as 26 means of 4"
    assert session.samples_read == n and len(session) == 26
    groups = [slice(a, min(a + 4, n)) for a in range(0, n, 4)]
    assert session.time_s == pytest.approx([t[g].mean() for g in groups], rel=1e-12)
    assert session.raw == pytest.approx([raw[g].mean() for g in groups], rel=1e-12)
    assert session.aux["temp_c"] == pytest.approx([20 + np.arange(n)[g].mean() for g in groups])
    assert session.means.raw_low.tolist() == [raw[g].min() for g in groups]
    assert session.means.raw_high.tolist() == [raw[g].max() for g in groups]
    assert session.settled is not None
    assert session.settled.tolist() == [bool(settled[g].all()) for g in groups]
    # Within the bound: the samples themselves, as the whole read gives them.
    whole = session_from_table(read_table(path), settled_column="settled")
    short = read_session(path, settled_column="settled", max_rows=n)
    assert short.means is None and short.raw.tobytes() == whole.raw.tobytes()


def test_time_going_backwards_names_the_same_line_as_the_whole_read(tmp_path, monkeypatch):
    monkeypatch.setattr(csv_chunks, "CHUNK_BYTES", 97)
    rows = [f"{i / 10:g},0,{i}\n" for i in range(60)]
    rows[41] = "1.0,0,41\n"  # back from 4.0 s
    path = tmp_path / "s.csv"
    path.write_text("time_s,ref_dps,raw\n" + "".join(rows))
    with pytest.raises(CanicalError) as whole:
        read_session(path, max_rows=100)
    with pytest.raises(CanicalError) as means:
        read_session(path, max_rows=10)
    assert str(means.value) == str(whole.value) and "line 43" in str(whole.value)


@pytest.mark.parametrize("seed", SEEDS)
def test_calibration_on_means_gives_the_set_within_the_fits_tolerance(tmp_path, seed):
    rates = np.concatenate([paper_rates(), paper_rates()[::-1]])
    session = sweep_session(GyroModel(), rates, dwell_s=2.3, fs_hz=1000.0, seed=seed)
    path = _write(tmp_path, session)
    full = calibrate(read_session(path), CalibrateOptions(), sensor_id="S", axis="z")
    reduced_session = read_session(path, max_rows=len(session) // 5)  # k = 5
    assert reduced_session.means is not None and reduced_session.means.k == 5
    reduced = calibrate(reduced_session, CalibrateOptions(), sensor_id="S", axis="z")
    a, b = full.report, reduced.report
    assert b.read_as_means == reduced_session.means.line() and a.read_as_means is None
    assert b.samples.total == a.samples.total == len(session)
    assert b.plateaus == a.plateaus and b.rates == a.rates
    assert b.samples.used == pytest.approx(a.samples.used, rel=0.01)
    # The same effects found, and the two sets' rates agree at every plateau within the
    # full set's own held-out error.
    names = [t.describe() for t in full.coefficients.terms]
    assert [t.describe() for t in reduced.coefficients.terms] == names
    means = full.base.points.dv + full.base.v0
    rate_full, _ = Corrector(full.coefficients).correct(means)
    rate_reduced, _ = Corrector(reduced.coefficients).correct(means)
    assert np.max(np.abs(rate_reduced - rate_full)) < a.held_out.rms_dps
    assert b.held_out.rms_dps == pytest.approx(a.held_out.rms_dps, rel=0.1)
    assert b.noise.per_sample_dps == pytest.approx(a.noise.per_sample_dps, rel=0.05)
    assert isinstance(a.allan, NoiseAnalysis) and isinstance(b.allan, NoiseAnalysis)
    arw_a, arw_b = a.allan.terms.arw, b.allan.terms.arw
    assert arw_a.resolved and arw_b.resolved
    assert arw_b.value == pytest.approx(arw_a.value, rel=0.1)
    assert b.allan.samples_per_point == 5 and b.allan.tau_range_s[0] == pytest.approx(0.005)


@pytest.mark.parametrize("seed", SEEDS)
@pytest.mark.parametrize("declared", [False, True])
def test_no_rail_hit_is_lost_in_the_means(tmp_path, seed, declared):
    session = sweep_session(CLIPPING, paper_rates(), dwell_s=4.0, seed=seed)
    if declared:
        session = replace(session, meta={**session.meta, "rail": "-20001,20000"})
    path = _write(tmp_path, session)
    options = CalibrateOptions(segments=3, order=2, extend=False)
    full = {p.rate_dps for p in fit_base(read_session(path), options).left_out}
    for bound in (len(session) // 3, len(session) // 10):
        reduced = read_session(path, max_rows=bound)
        assert reduced.means is not None
        left = {p.rate_dps for p in fit_base(reduced, options).left_out}
        assert full <= left, bound  # every plateau at the rail in the samples is at it in the means
        assert {-60.0, -57.0, 51.0, 54.0, 57.0, 60.0} <= left
        assert all(abs(r) > 48 for r in left)


def test_rail_hits_count_rows_with_any_sample_at_the_rail(tmp_path):
    """One sample in a hundred at the rail leaves a plateau out; the means alone never reach it."""
    rate = np.repeat([0.0, 10.0, 20.0, 30.0, 40.0], 4000)
    time_s = np.arange(rate.size) / 1000.0
    rng = np.random.default_rng(3)
    raw = 1000.0 + 400.0 * rate + rng.normal(0.0, 5.0, rate.size)
    last = rate == 40.0
    at_rail = np.flatnonzero(last)[::80]  # 1.25 % of the plateau's samples, spread out
    raw[at_rail] = 20000.0
    session = Session(time_s, raw, rate, meta={"rail": "-20000,20000"})
    path = _write(tmp_path, session)
    options = CalibrateOptions(segments=1, order=1, extend=False)
    assert [p.rate_dps for p in fit_base(read_session(path), options).left_out] == [40.0]
    reduced = read_session(path, max_rows=rate.size // 8)
    assert reduced.means is not None and np.max(reduced.raw) < 19000.0
    assert [p.rate_dps for p in fit_base(reduced, options).left_out] == [40.0]
    assert np.max(reduced.means.raw_high) == 20000.0


def test_calibrate_prints_how_the_session_was_read(tmp_path, monkeypatch, capsys):
    rates = np.concatenate([paper_rates(), paper_rates()[::-1]])
    session = sweep_session(GyroModel(), rates, dwell_s=2.3, fs_hz=1000.0, seed=4)
    path = _write(tmp_path, session)
    monkeypatch.setattr(row_means, "REDUCE_ABOVE_ROWS", 60_000)
    monkeypatch.setenv("CANICAL_PROGRESS", "1")
    out = tmp_path / "set.yaml"
    assert main(["calibrate", str(path), "-o", str(out), "--no-extend"]) == 0
    captured = capsys.readouterr()
    line = f"{len(session):,} rows read as {-(-len(session) // 4):,} means of 4"
    assert f"input      {line}" in captured.out
    assert f"calibrate: {line}" in captured.err


def test_a_tables_own_file_aligns_to_the_means_as_to_the_samples(tmp_path, monkeypatch, capsys):
    case = own_clock_case(0, gyro=GyroModel(), fs_hz=100.0, offset_s=5000.25, drift_ppm=-75.0)
    path = _write(tmp_path, case.session)  # no ref_dps column: the table's file gives it
    table = tmp_path / "table.csv"
    table.write_text(table_csv(case.table))
    args = ["calibrate", str(path), "--reference", str(table), "--no-extend", "--segments", "3",
            "--order", "2", "--report", str(tmp_path / "r.json")]
    clocks = []
    for bound in (None, len(case.session) // 4):
        if bound:
            monkeypatch.setattr(row_means, "REDUCE_ABOVE_ROWS", bound)
        assert main([*args, "-o", str(tmp_path / f"set-{bound}.yaml")]) == 0
        report = json.loads((tmp_path / "r.json").read_text())
        assert ("read_as_means" in report) == bool(bound)
        clocks.append(report["reference_clock"])
    capsys.readouterr()
    samples, means = clocks
    assert means["rate_changes_matched"] == samples["rate_changes_matched"]
    assert means["offset_s"] == pytest.approx(samples["offset_s"], abs=0.01)  # a mean is 40 ms here
    assert means["drift_ppm"] == pytest.approx(samples["drift_ppm"], abs=5.0)
