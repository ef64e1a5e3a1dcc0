"""``canical noise`` on static records, and the Allan analysis of the zero-rate plateaus in the
calibrate report. Truth is the white rate noise put into each record (ARW = σ/√fs, in deg/√h)."""

from __future__ import annotations

import json
from dataclasses import replace
from pathlib import Path

import can
import numpy as np
import pytest
from support.allan_noise import flicker_rate, rate_random_walk
from support.daemon_fixtures import DBC, write_sets
from support.sessions import write_session

from canical.calibration.pipeline import CalibrateOptions, calibrate
from canical.commands.cli import main
from canical.frames.codec import load_dbc
from canical.sets import coefficient_file
from canical.sets.corrector import Corrector
from canical.sim.gyro import GyroModel
from canical.sim.sessions import paper_session, sweep_session

FS = 100.0
PNG = b"\x89PNG\r\n\x1a\n"


def static_csv(path: Path, t: np.ndarray, columns: dict[str, np.ndarray]) -> Path:
    names = ["time_s", *columns]
    data = np.column_stack([t, *columns.values()])
    rows = "\n".join(",".join(f"{v:.9g}" for v in row) for row in data)
    path.write_text(",".join(names) + "\n" + rows + "\n")
    return path


def read_terms(out: str) -> dict[str, str]:
    lines = out.strip().splitlines()[1:]
    return {line[:18].strip(): line[18:].strip() for line in lines}


@pytest.mark.parametrize("seed", [1, 2])
def test_noise_of_a_rate_column_with_lost_rows(tmp_path: Path, capsys, seed: int) -> None:
    """Ten minutes at rest, 3% of the rows lost in bursts: ARW as put in, the rest not claimed."""
    rng = np.random.default_rng(seed)
    arw = rng.uniform(0.1, 1.0)
    n = int(600 * FS)
    t = np.arange(n) / FS
    rate = 0.02 + arw / 60.0 * np.sqrt(FS) * rng.standard_normal(n)
    keep = np.ones(n, dtype=bool)
    for start in rng.choice(n - 50, size=40, replace=False):
        keep[start : start + 45] = False  # ~3% lost, in bursts of 45 rows
    path = static_csv(tmp_path / "static.csv", t[keep], {"rate_dps": rate[keep], "temp_c": 25 + 0 * t[keep]})
    plot, report = tmp_path / "adev.png", tmp_path / "noise.json"
    assert main(["noise", str(path), "--plot", str(plot), "--json", str(report)]) == 0
    out = capsys.readouterr().out
    terms = read_terms(out)
    assert float(terms["angle random walk"].split()[0]) == pytest.approx(arw, rel=0.03)
    assert terms["rate random walk"].startswith("not resolved")
    assert "tau 0.01 to " in out.splitlines()[0]
    assert plot.read_bytes().startswith(PNG)
    analysis = json.loads(report.read_text())
    assert analysis["records"] > 1  # cut at the lost rows, not averaged across them
    assert analysis["terms"]["arw"]["interval"][0] < analysis["terms"]["arw"]["value"]
    assert analysis["terms"]["rrw"]["resolved"] is False and analysis["terms"]["rrw"]["upper_bound"] > 0


def _static_counts(rng: np.random.Generator, cset, n: int, arw: float) -> tuple[np.ndarray, float]:
    """Raw counts at rest whose rate noise through the set is ``arw`` deg/√h."""
    corrector = Corrector(cset)
    slope = float(np.diff(corrector.correct(np.array([cset.v0 - 50.0, cset.v0 + 50.0]))[0])[0] / 100.0)
    counts_sigma = arw / 60.0 * np.sqrt(FS) / slope
    return cset.v0 + counts_sigma * rng.standard_normal(n), slope


def test_noise_of_raw_counts_through_a_coefficient_set(tmp_path: Path, capsys) -> None:
    sets = write_sets(tmp_path)
    cset = coefficient_file.load(sets["z"])
    rng = np.random.default_rng(5)
    n = int(300 * FS)
    raw, _ = _static_counts(rng, cset, n, 0.4)
    path = static_csv(tmp_path / "raw.csv", np.arange(n) / FS, {"raw": np.round(raw, 3)})
    assert main(["noise", str(path), "--coefficients", str(sets["z"])]) == 0
    terms = read_terms(capsys.readouterr().out)
    assert float(terms["angle random walk"].split()[0]) == pytest.approx(0.4, rel=0.03)


def test_noise_of_a_can_log(tmp_path: Path, capsys) -> None:
    """IMU_RAW frames of a sensor at rest in a candump log, converted with the set's axis and model."""
    sets = write_sets(tmp_path)
    cset = coefficient_file.load(sets["z"])
    rng = np.random.default_rng(6)
    n = int(300 * FS)
    raw, slope = _static_counts(rng, cset, n, 0.8)
    raw_counts = np.round(raw)  # the frame carries whole counts: their rounding is white noise too
    expected = np.sqrt((0.8 / 60.0) ** 2 + (slope / np.sqrt(12.0)) ** 2 / FS) * 60.0
    msg = load_dbc(DBC).get_message_by_name("IMU_RAW")
    log = tmp_path / "rest.log"
    with can.Logger(str(log)) as logger:
        for i, r in enumerate(raw_counts):
            data = msg.encode({"GyroRawX": 0, "GyroRawY": 0, "GyroRawZ": int(r), "Temperature": 25.0,
                               "Counter": i & 0xF, "SensorFault": 0})
            logger.on_message_received(can.Message(timestamp=1e9 + i / FS, arbitration_id=msg.frame_id,
                                                   is_extended_id=False, data=data))
    assert main(["noise", str(log), "--coefficients", str(sets["z"]), "--dbc", str(DBC)]) == 0
    terms = read_terms(capsys.readouterr().out)
    assert float(terms["angle random walk"].split()[0]) == pytest.approx(expected, rel=0.03)


def test_noise_errors_are_one_line(tmp_path: Path, capsys) -> None:
    t = np.arange(100) / FS
    rate = np.zeros(100)
    back = t.copy()
    back[40] = back[38]  # row 41 earlier than row 40: the file's line 42 (after the header)
    cases = [
        (static_csv(tmp_path / "a.csv", back, {"rate_dps": rate}), [], "line 42: time goes backwards"),
        (static_csv(tmp_path / "b.csv", t, {"raw": rate}), [], "no rate_dps column: name the rate column"),
        (static_csv(tmp_path / "c.csv", t, {"w": rate}), ["--column", "v"], "no v column"),
        (static_csv(tmp_path / "d.csv", t[:4], {"rate_dps": rate[:4]}), [], "no evenly sampled stretch"),
        (tmp_path / "none.csv", [], "file not found"),
    ]
    for path, extra, message in cases:
        plot = tmp_path / "p.png"
        assert main(["noise", str(path), *extra, "--plot", str(plot)]) == 2, message
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], err
        assert not plot.exists()
    log = tmp_path / "x.log"
    log.write_text("(1.0) can0 190#0000000000000000\n")
    assert main(["noise", str(log)]) == 2
    assert "give --coefficients" in capsys.readouterr().err


def test_calibrate_report_has_the_allan_deviation_of_the_zero_rate_plateaus(tmp_path: Path, capsys) -> None:
    """Four 30 s zero-rate plateaus in a sweep: ARW as the simulated white noise, τ range up to
    a third of a plateau, and no rate random walk claimed from 2 minutes of data."""
    gyro = GyroModel()
    rates = np.array([0.0, 10.0, 30.0, 0.0, -10.0, -30.0, 0.0, 20.0, -20.0, 0.0, 50.0, -50.0])
    session = sweep_session(gyro, rates, dwell_s=30.0, fs_hz=200.0, seed=3)
    path = write_session(tmp_path / "s.csv", session)
    rep = tmp_path / "report"
    assert main(["calibrate", str(path), "-o", str(tmp_path / "c.yaml"), "--no-extend",
                 "--report-dir", str(rep)]) == 0
    out = capsys.readouterr().out
    assert "noise      angle random walk" in out and "rate random walk not resolved" in out
    allan = json.loads((rep / "report.json").read_text())["allan"]
    assert allan["records"] == 4 and allan["source"] == "4 zero-rate plateaus"
    # white noise of 0.08 deg/s per sample at 200 Hz; the counts' rounding adds a little
    assert allan["terms"]["arw"]["value"] == pytest.approx(0.08 / np.sqrt(200.0) * 60.0, rel=0.1)
    assert allan["tau_range_s"][1] <= 30.0 / 3
    assert not allan["terms"]["rrw"]["resolved"]
    md = (rep / "report.md").read_text()
    assert "Allan deviation of the zero-rate plateaus" in md and "![allan.png](allan.png)" in md
    assert (rep / "allan.png").read_bytes().startswith(PNG)


def test_closed_loop_blames_no_channel_for_bias_instability_and_rate_random_walk() -> None:
    """A clean sensor whose noise is not white (BI 50 deg/h, RRW 200 deg/h/√h, far worse than a
    tactical MEMS part) beside a drifting temperature channel: the slow wander looks like an
    effect of time or temperature, but the loop's held-out acceptance must not add one."""
    gyro = GyroModel()
    session = paper_session(gyro, seed=1, sweeps=2, aux={
        "temp_c": lambda t, w, rng: 25.0 + 0.004 * t + 0.05 * rng.standard_normal(t.size)})
    rng = np.random.default_rng(51)
    wander = flicker_rate(rng, len(session), 200.0, 50.0) + rate_random_walk(rng, len(session), 200.0, 200.0)
    noisy = replace(session, raw=np.round(session.raw + gyro.sensitivity * wander))
    result = calibrate(noisy, CalibrateOptions(), sensor_id="SIM", axis="z")
    assert result.report.effects == ()
    assert result.coefficients.terms == ()


@pytest.mark.parametrize(("noise_dps", "seed"), [(0.08, 0), (0.2, 3)])
def test_the_set_carries_the_angle_random_walk_it_measured(noise_dps: float, seed: int) -> None:
    """fit.arw_deg_rt_h (what bias tracking tells a standstill by) is the sensor's white noise:
    N = σ_sample·√Δt, within the read-out's own interval for a clean sensor."""
    gyro = GyroModel(noise_dps=noise_dps)
    session = paper_session(gyro, seed=seed)
    result = calibrate(session, CalibrateOptions(extend=False), sensor_id="SIM", axis="z")
    fs = 1.0 / float(np.median(np.diff(session.time_s)))
    truth = noise_dps / np.sqrt(fs) * 60.0
    assert result.coefficients.fit["arw_deg_rt_h"] == pytest.approx(truth, rel=0.1)


@pytest.mark.parametrize(("turning", "warned"), [(True, True), (False, False)])
def test_a_record_that_moves_is_named_as_such(tmp_path: Path, capsys, turning: bool, warned: bool) -> None:
    """A record with motion gave a rate random walk of 2.95e5 deg/h/√h without a word."""
    rng = np.random.default_rng(4)
    n = int(300 * FS)
    t = np.arange(n) / FS
    turns = np.where((t % 60) < 20, 30.0, 0.0) if turning else 0.0  # 20 s at 30 deg/s every minute
    rate = 0.02 + turns + 0.3 / 60.0 * np.sqrt(FS) * rng.standard_normal(n)
    path = static_csv(tmp_path / "record.csv", t, {"rate_dps": rate})
    assert main(["noise", str(path)]) == 0
    err = capsys.readouterr().err
    assert ("is not at rest: its 1 s means span 30 deg/s" in err) is warned, err
    assert len(err.strip().splitlines()) == int(warned)
