"""``apply --track-bias --field-log DIR``: a recorded drive's standstill decisions and power-ons as
field records, the same from the streamed and the whole-file path, the power-on count continuing
the folder's; the options' misuse is one line."""

from __future__ import annotations

from datetime import UTC, datetime
from pathlib import Path

import pytest
from test_apply_track_bias import drive_csv

from canical.commands.cli import main
from canical.fieldlog import segments
from canical.fieldlog.record import POWER_ON, FieldRecord


def records(folder: Path) -> list[FieldRecord]:
    return [r for s in segments.read_segments(segments.segment_paths(folder), print) for r in s.records]


def apply(set_path: Path, csv: Path, folder: Path, *extra: str) -> int:
    return main(["apply", str(set_path), str(csv), "--track-bias", "--arw", "0.3", "--standstill-column",
                 "speed_mps", "-o", str(folder / "out.csv"), "--field-log", str(folder / "field"),
                 "--vehicle-id", "car-7", "--drive-start", "2026-11-27T08:00:00Z", *extra])


def test_a_drive_gives_one_record_per_standstill_and_per_power_on(tmp_path: Path,
                                                                 capsys: pytest.CaptureFixture[str]) -> None:
    set_path, csv, _ = drive_csv(tmp_path)
    assert apply(set_path, csv, tmp_path) == 0
    out = capsys.readouterr().out
    got = records(tmp_path / "field")
    stops = [r for r in got if r.decision != POWER_ON]
    assert len(stops) == out.count("apply: standstill") and stops
    assert [r.power_on for r in got if r.decision == POWER_ON] == [0, 1, 2]  # the drive's three power-ons
    assert [r.utc for r in got] == sorted(r.utc for r in got)
    assert got[0].utc == datetime(2026, 11, 27, 8, tzinfo=UTC) and got[0].vehicle_id == "car-7"
    assert all(r.temp_c is not None for r in stops) and f"into {tmp_path / 'field'}" in out


def test_the_streamed_and_the_whole_file_paths_write_the_same_records(tmp_path: Path) -> None:
    set_path, csv, _ = drive_csv(tmp_path)
    (tmp_path / "a").mkdir()
    (tmp_path / "b").mkdir()
    assert apply(set_path, csv, tmp_path / "a") == 0  # streamed
    assert apply(set_path, csv, tmp_path / "b", "--report-dir", str(tmp_path / "b" / "report")) == 0  # whole
    assert records(tmp_path / "a" / "field") == records(tmp_path / "b" / "field")


def test_a_second_drive_continues_the_power_on_count(tmp_path: Path) -> None:
    set_path, csv, _ = drive_csv(tmp_path)
    assert apply(set_path, csv, tmp_path) == 0
    assert apply(set_path, csv, tmp_path) == 0
    counts = [r.power_on for r in records(tmp_path / "field") if r.decision == POWER_ON]
    assert counts == [0, 1, 2, 3, 4, 5]


@pytest.mark.parametrize(("argv", "message"), [
    (["--field-log", "f"], "need --track-bias"),
    (["--track-bias", "--vehicle-id", "v"], "--vehicle-id and --drive-start need --field-log"),
    (["--track-bias", "--field-log", "f", "--vehicle-id", "a b"], "--vehicle-id 'a b'"),
    (["--track-bias", "--field-log", "f", "--drive-start", "yesterday"], "--drive-start 'yesterday'"),
])
def test_misuse_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str],
                            message: str) -> None:
    set_path, csv, _ = drive_csv(tmp_path)
    assert main(["apply", str(set_path), str(csv), "-o", str(tmp_path / "o.csv"), *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1
    assert not (tmp_path / "f").exists()
