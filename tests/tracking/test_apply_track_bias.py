"""``canical apply --track-bias``: a simulated drive as a CSV of raw counts, replayed row by row."""

from __future__ import annotations

import functools
from pathlib import Path

import numpy as np
import pytest
from support.daemon_fixtures import DBC, base_set

from canical.commands.cli import main
from canical.sets import coefficient_file
from canical.sets.coefficients import CoefficientSet
from canical.sets.corrector import Corrector
from canical.sim.drive import simulate_drive
from canical.tracking.config import TrackerConfig
from canical.tracking.replay import replay


@functools.cache
def z_set() -> CoefficientSet:
    return base_set("z")


def drive_csv(folder: Path, seed: int = 0) -> tuple[Path, Path, np.ndarray]:
    """The set's file and a drive CSV whose raw counts the set turns into the drive's rates."""
    cset = z_set()
    set_path = folder / "z.yaml"
    coefficient_file.save(set_path, cset)
    drive = simulate_drive(seed)
    lo, hi = cset.span_raw
    grid = np.linspace(lo, hi, 20001)
    rate_grid, _ = Corrector(cset).correct(grid)
    raw = np.round(np.interp(drive.rate_dps, rate_grid, grid), 3)
    path = folder / "drive.csv"
    lines = [f"# sensor: {cset.sensor_id}", "time_s,raw,temp_c,speed_mps"]
    lines += [f"{t:.2f},{r:.3f},{c:.2f},{s:.3f}" for t, r, c, s in
              zip(drive.time_s, raw, drive.temp_c, drive.speed_mps, strict=True)]
    path.write_text("\n".join(lines) + "\n")
    return set_path, path, drive.bias_dps


def test_apply_track_bias_appends_the_replayed_bias(tmp_path: Path,
                                                    capsys: pytest.CaptureFixture[str]) -> None:
    set_path, csv, true_bias = drive_csv(tmp_path)
    out, report = tmp_path / "out.csv", tmp_path / "report"
    assert main(["apply", str(set_path), str(csv), "--track-bias", "--arw", "0.3",
                 "--standstill-column", "speed_mps", "-o", str(out), "--report-dir", str(report)]) == 0
    text = capsys.readouterr().out
    assert "standstill" in text and "adopted" in text and "refused" in text
    lines_in, lines_out = csv.read_text().splitlines(), out.read_text().splitlines()
    assert lines_out[1] == lines_in[1] + ",rate_dps,out_of_span,bias_dps"
    assert all(o.startswith(i + ",") for i, o in zip(lines_in[2:], lines_out[2:], strict=True))
    table = np.loadtxt(out, delimiter=",", skiprows=2)
    rate, bias = table[:, 4], table[:, 6]
    # the same step, row by row, on the rates as written: the column is the replay's output
    again = replay(table[:, 0], rate, TrackerConfig(arw_deg_rt_h=0.3, cue_threshold=0.1),
                   temp_c=table[:, 2], cue=table[:, 3])
    assert np.max(np.abs(again.bias_dps[:, 0] - bias)) <= 1e-5  # 6 decimals in the file, rates rounded
    driving = table[:, 3] > 0
    assert np.sqrt(np.mean((bias - true_bias)[driving] ** 2)) < 0.03
    for name in ("drive.md", "standstills.csv", "heading.png", "bias_vs_temperature.png"):
        assert (report / name).stat().st_size > 0
    assert "beyond the plausibility bound" in (report / "drive.md").read_text() or \
        "cue says moving" in (report / "drive.md").read_text()


@pytest.mark.parametrize(("extra", "message"), [
    (["--standstill-column", "nope"], "no column 'nope'"),
    (["--arw", "-1"], "arw_deg_rt_h must be a positive number"),
])
def test_bad_tracking_inputs_are_one_line_and_write_nothing(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], extra: list[str], message: str) -> None:
    set_path, csv, _ = drive_csv(tmp_path)
    out, report = tmp_path / "out.csv", tmp_path / "report"
    code = main(["apply", str(set_path), str(csv), "--track-bias", *extra, "-o", str(out),
                 "--report-dir", str(report)])
    err = capsys.readouterr().err
    assert code == 2 and message in err and len(err.strip().splitlines()) == 1
    assert not out.exists() and not report.exists()


def test_tracking_options_need_track_bias(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    set_path, csv, _ = drive_csv(tmp_path)
    assert main(["apply", str(set_path), str(csv), "--report-dir", str(tmp_path / "r"),
                 "-o", str(tmp_path / "o.csv")]) == 2
    assert "need --track-bias" in capsys.readouterr().err


def test_a_drive_without_time_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    set_path, csv, _ = drive_csv(tmp_path)
    lines = csv.read_text().splitlines()
    lines[1] = lines[1].replace("time_s", "t")
    csv.write_text("\n".join(lines) + "\n")
    assert main(["apply", str(set_path), str(csv), "--track-bias", "-o", str(tmp_path / "o.csv")]) == 2
    assert "needs a time_s column" in capsys.readouterr().err
    assert not (tmp_path / "o.csv").exists()


def drive_log(folder: Path) -> tuple[Path, Path, np.ndarray]:
    """The drive's first power-on as a candump log: IMU_RAW (z counts, temperature), IMU_AUX uptime."""
    import can

    from canical.frames.codec import load_dbc

    set_path, csv, _ = drive_csv(folder)
    table = np.loadtxt(csv, delimiter=",", skiprows=2)
    first = table[: int(np.argmax(np.diff(table[:, 0]) < 0)) + 1]
    db = load_dbc(DBC)
    raw, aux = db.get_message_by_name("IMU_RAW"), db.get_message_by_name("IMU_AUX")
    log = folder / "drive.log"
    with can.Logger(str(log)) as logger:
        for i, (t, counts, temp, _speed) in enumerate(first):
            stamp = 1_700_000_000.0 + t
            if i % 10 == 0:
                logger.on_message_received(can.Message(
                    timestamp=stamp, arbitration_id=aux.frame_id, is_extended_id=False,
                    data=aux.encode({"SupplyVoltage": 5.0, "Uptime": float(t), "AuxCounter": 0})))
            logger.on_message_received(can.Message(
                timestamp=stamp, arbitration_id=raw.frame_id, is_extended_id=False,
                data=raw.encode({"GyroRawX": 0, "GyroRawY": 0, "GyroRawZ": round(counts),
                                 "Temperature": round(float(temp), 1), "Counter": i & 0xF,
                                 "SensorFault": 0})))
    return set_path, log, first


def test_apply_track_bias_on_a_can_log(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    set_path, log, _ = drive_log(tmp_path)
    out = tmp_path / "out.csv"
    assert main(["apply", str(set_path), str(log), "--dbc", str(DBC), "--input", "temp_c=IMU_RAW.Temperature",
                 "--input", "time_s=IMU_AUX.Uptime", "--track-bias", "--arw", "0.3", "-o", str(out)]) == 0
    assert "adopted" in capsys.readouterr().out
    lines = out.read_text().splitlines()
    at = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    assert lines[at] == "time_s,raw,temp_c,rate_dps,out_of_span,bias_dps"
    table = np.loadtxt(out, delimiter=",", skiprows=at + 1)
    again = replay(table[:, 0], table[:, 3], TrackerConfig(arw_deg_rt_h=0.3), temp_c=table[:, 2])
    assert np.max(np.abs(again.bias_dps[:, 0] - table[:, 5])) <= 1e-5
    assert abs(table[-1, 5] - 0.35 - 0.012 * (table[-1, 2] - 20.0)) < 0.03
    assert main(["apply", str(set_path), str(log), "--dbc", str(DBC), "--track-bias", "--standstill-column",
                 "speed", "-o", str(tmp_path / "o2.csv")]) == 2
    assert "map it to a signal with --input speed=MESSAGE.Signal" in capsys.readouterr().err
    assert not (tmp_path / "o2.csv").exists()


@pytest.mark.parametrize("block_bytes", [300, 7_000, 1 << 22])
def test_apply_track_bias_streamed_in_blocks_writes_what_the_whole_file_gives(
        tmp_path: Path, capsys: pytest.CaptureFixture[str], monkeypatch: pytest.MonkeyPatch,
        block_bytes: int) -> None:
    """Without --report-dir the drive is read, corrected, tracked and written a block at a time
    (the tracker carried across blocks); the file is byte for byte the whole-file run's (with
    --report-dir), and so are the standstills printed."""
    from canical.sessions import csv_chunks

    set_path, csv, _ = drive_csv(tmp_path, seed=2)
    args = [str(set_path), str(csv), "--track-bias", "--arw", "0.3", "--standstill-column", "speed_mps"]
    whole = tmp_path / "whole.csv"
    assert main(["apply", *args, "-o", str(whole), "--report-dir", str(tmp_path / "r")]) == 0
    whole_text = capsys.readouterr().out
    monkeypatch.setattr(csv_chunks, "CHUNK_BYTES", block_bytes)
    streamed = tmp_path / "streamed.csv"
    assert main(["apply", *args, "-o", str(streamed)]) == 0
    streamed_text = capsys.readouterr().out
    assert csv_chunks.read_head(csv) is not None  # so it streamed
    assert streamed.read_bytes() == whole.read_bytes()
    events = [line for line in whole_text.splitlines() if "standstill" in line]
    assert events and events == [line for line in streamed_text.splitlines() if "standstill" in line]


def short_drive_without_temperature(folder: Path) -> tuple[Path, Path]:
    """7 s still, a 95 deg/s turn of 2 s, 3 s still: no temperature column (issue 33, point 9)."""
    cset = z_set()
    set_path = folder / "z.yaml"
    coefficient_file.save(set_path, cset)
    rng = np.random.default_rng(3)
    t = np.arange(1200) / 100.0
    rate = np.where((t >= 7.0) & (t < 9.0), 95.0, 0.3) + 0.05 * rng.standard_normal(t.size)
    lo, hi = cset.span_raw
    grid = np.linspace(lo, hi, 20001)
    rate_grid, _ = Corrector(cset).correct(grid)
    raw = np.interp(rate, rate_grid, grid)
    path = folder / "short.csv"
    lines = [f"# sensor: {cset.sensor_id}", "time_s,raw",
             *(f"{a:.2f},{b:.4f}" for a, b in zip(t, raw, strict=True))]
    path.write_text("\n".join(lines) + "\n")
    return set_path, path


def test_a_short_drive_without_temperature_claims_no_temperature_and_no_effect(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """No "at 25.0 °C" (nobody measured it), no effect concluded from a few windows over seconds,
    and the 95 deg/s turn is not listed as a standstill refused for being short."""
    set_path, csv = short_drive_without_temperature(tmp_path)
    report = tmp_path / "report"
    assert main(["apply", str(set_path), str(csv), "--track-bias", "--arw", "0.3", "-o",
                 str(tmp_path / "out.csv"), "--report-dir", str(report)]) == 0
    out = capsys.readouterr().out
    events = [line for line in out.splitlines() if "standstill " in line and "standstills used" not in line]
    assert events and all("temperature not recorded" in line for line in events), out
    assert "°C" not in out and "windows learned" not in out
    assert all("+95" not in line and "+94" not in line for line in events), events
    text = (report / "drive.md").read_text()
    assert "25.0" not in text and "not recorded" in text
    assert "the effect the set lacks" not in text and "Too little evidence to tell: " in text
    assert "0 windows learned" not in text
    assert (report / "bias_vs_time.png").stat().st_size > 0
    assert not (report / "bias_vs_temperature.png").exists()
    assert ",," in (report / "standstills.csv").read_text().splitlines()[1]  # temp_c left empty
