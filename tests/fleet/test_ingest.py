"""``canical fleet ingest``: segments into a Parquet dataset by vehicle and day; ingesting the same
segment twice adds nothing, a grown segment adds only its new records, a damaged one is skipped
with one line naming it."""

from __future__ import annotations

from pathlib import Path

import pyarrow as pa
import pytest

from canical.commands.cli import main
from canical.fieldlog import segments
from canical.fieldlog.segments import SegmentWriter
from canical.fleet import dataset
from canical.sim.fleet import simulate_vehicle


def table(target: Path) -> pa.Table:
    return pa.concat_tables([dataset.read_vehicle(v) for v in dataset.vehicle_folders(target)])


def write_vehicle(folder: Path, index: int, days: int = 3) -> list:
    records = simulate_vehicle(index, days, seed=1)[1]
    for number, data in enumerate(segments.pack(records, segment_bytes=4000)):
        (folder / f"veh-{index:05d}").mkdir(parents=True, exist_ok=True)
        (folder / f"veh-{index:05d}" / segments.segment_name(number)).write_bytes(data)
    return records


def test_ingesting_the_same_segments_twice_adds_nothing(tmp_path: Path,
                                                        capsys: pytest.CaptureFixture[str]) -> None:
    logs, target = tmp_path / "logs", tmp_path / "ds"
    records = write_vehicle(logs, 0) + write_vehicle(logs, 1)
    assert main(["fleet", "ingest", str(logs), "-o", str(target)]) == 0
    first = table(target)
    assert first.num_rows == len(records)
    assert sorted(first.column("record_id").to_pylist()) == sorted(dataset.record_id(r) for r in records)
    days = {p.name for v in dataset.vehicle_folders(target) for p in v.iterdir()}
    assert days == {"day=2026-10-01", "day=2026-10-02", "day=2026-10-03"}
    files = sorted(target.rglob("*.parquet"))
    assert main(["fleet", "ingest", str(logs), str(logs / "veh-00000"), "-o", str(target)]) == 0
    assert f"0 added to {target}" in capsys.readouterr().out.splitlines()[-1]
    assert sorted(target.rglob("*.parquet")) == files and table(target).equals(first)


def test_a_segment_that_grew_adds_only_its_new_records(tmp_path: Path) -> None:
    logs, target = tmp_path / "logs", tmp_path / "ds"
    records = simulate_vehicle(2, 2, seed=1)[1]
    writer = SegmentWriter(logs, max_bytes=10**9)
    for r in records[:10]:
        writer.add(r)
    writer.flush()
    assert main(["fleet", "ingest", str(logs), "-o", str(target)]) == 0
    for r in records[10:]:
        writer.add(r)
    writer.flush()
    assert main(["fleet", "ingest", str(logs), "-o", str(target)]) == 0
    rows = table(target)
    assert rows.num_rows == len(records) and len(set(rows.column("record_id").to_pylist())) == len(records)


def test_a_damaged_segment_is_skipped_with_one_line(tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    logs, target = tmp_path / "logs", tmp_path / "ds"
    write_vehicle(logs, 3)
    victim = segments.segment_paths(logs / "veh-00003")[1]
    victim.write_bytes(victim.read_bytes()[:-30])
    assert main(["fleet", "ingest", str(logs), "-o", str(target)]) == 0
    captured = capsys.readouterr()
    assert captured.err.count(str(victim)) == 1 and "Traceback" not in captured.err
    assert "1 damaged, skipped" in captured.out


def test_a_missing_source_is_one_line_and_nothing_is_written(tmp_path: Path,
                                                             capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["fleet", "ingest", str(tmp_path / "nowhere"), "-o", str(tmp_path / "ds")]) == 2
    assert "no such file or folder" in capsys.readouterr().err and not (tmp_path / "ds").exists()
