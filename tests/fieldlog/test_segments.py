"""The field log's records and segments: a round trip gives the records back exactly, a damaged
segment is skipped by the reader with one line naming it, rotation keeps the directory bounded."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta
from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from canical.fieldlog import segments
from canical.fieldlog.record import ADOPTED, DECISIONS, POWER_ON, FieldRecord, RecordError
from canical.fieldlog.segments import SegmentError, SegmentWriter

finite = st.floats(allow_nan=False, allow_infinity=False, width=64)
names = st.text(st.characters(codec="utf-8", exclude_categories=("Cs",)), min_size=1, max_size=12)


@st.composite
def field_records(draw: st.DrawFn) -> FieldRecord:
    axes = tuple(draw(st.lists(st.sampled_from("xyz"), min_size=1, max_size=3, unique=True)))
    n = len(axes)
    micros = draw(st.integers(0, 10**15))
    return FieldRecord(
        utc=datetime(2020, 1, 1, tzinfo=UTC) + timedelta(microseconds=micros), vehicle_id=draw(names),
        sensor_id=draw(st.text(max_size=12)), set_id=draw(st.integers(0, 2**32 - 1)),
        power_on=draw(st.integers(0, 10**6)), since_power_on_s=draw(finite),
        temp_c=draw(st.none() | finite), axes=axes,
        bias_dps=tuple(draw(st.lists(finite, min_size=n, max_size=n))),
        sigma_dps=tuple(draw(st.lists(finite.map(abs), min_size=n, max_size=n))),
        decision=draw(st.sampled_from(DECISIONS)), reason=draw(st.text(max_size=40)))


def record(i: int = 0, **changes: object) -> FieldRecord:
    fields: dict[str, object] = dict(
        utc=datetime(2026, 11, 27, 9, 0, tzinfo=UTC) + timedelta(seconds=i), vehicle_id="v001",
        sensor_id="LOT7-0042", set_id=0x1234ABCD, power_on=3, since_power_on_s=12.5 + i, temp_c=31.25,
        axes=("z",), bias_dps=(0.125,), sigma_dps=(0.004,), decision=ADOPTED, reason="3 still windows")
    fields.update(changes)
    return FieldRecord(**fields)  # type: ignore[arg-type]


@settings(max_examples=150, deadline=None)
@given(st.lists(field_records(), max_size=20), st.integers(0, 10**6))
def test_a_segment_gives_its_records_back_exactly(records: list[FieldRecord], number: int) -> None:
    assert segments.decode(segments.encode(number, records)) == (number, tuple(records))


@settings(max_examples=150, deadline=None)
@given(st.lists(field_records(), min_size=1, max_size=8), st.data())
def test_any_changed_or_cut_byte_is_refused_never_misread(records: list[FieldRecord],
                                                          data: st.DataObject) -> None:
    good = segments.encode(0, records)
    where = data.draw(st.integers(0, len(good) - 1))
    if data.draw(st.booleans()):
        bad = good[:where]
    else:
        bad = good[:where] + bytes([good[where] ^ data.draw(st.integers(1, 255))]) + good[where + 1:]
    try:
        got = segments.decode(bad)
    except SegmentError:
        return
    assert got == (0, tuple(records))  # only a change the format ignores (a trailing newline) passes


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.lists(st.lists(field_records(), max_size=6), min_size=1, max_size=6))
def test_what_the_writer_flushed_the_reader_reads_in_order(tmp_path: Path,
                                                            batches: list[list[FieldRecord]]) -> None:
    directory = tmp_path / f"log{len(list(tmp_path.iterdir()))}"
    writer = SegmentWriter(directory, max_bytes=10**9, segment_bytes=2000)
    for batch in batches:
        for r in batch:
            writer.add(r)
        writer.flush()
    lines: list[str] = []
    read = [r for s in segments.read_segments(segments.segment_paths(directory), lines.append)
            for r in s.records]
    assert read == [r for batch in batches for r in batch] and lines == []


@pytest.mark.parametrize("damage", ["flip", "truncate", "empty", "foreign", "bad record"])
def test_a_damaged_segment_is_skipped_with_one_line_naming_it(tmp_path: Path, damage: str) -> None:
    writer = SegmentWriter(tmp_path, max_bytes=10**9, segment_bytes=1)  # one segment per flush
    for i in range(3):
        writer.add(record(i))
        writer.flush()
    paths = segments.segment_paths(tmp_path)
    victim = paths[1]
    data = victim.read_bytes()
    victim.write_bytes({"flip": data.replace(b"0.125", b"0.126"), "truncate": data[: len(data) // 2],
                        "empty": b"", "foreign": b"\x00\xff" * 40,
                        "bad record": segments.encode(1, []).replace(b'"records":0', b'"records":1')
                        }[damage])
    lines: list[str] = []
    read = list(segments.read_segments(paths, lines.append))
    assert [s.path for s in read] == [paths[0], paths[2]]
    assert len(lines) == 1 and str(victim) in lines[0] and "\n" not in lines[0]


def test_rotation_keeps_the_directory_within_its_bound_oldest_removed_first(tmp_path: Path) -> None:
    writer = SegmentWriter(tmp_path, max_bytes=3000, segment_bytes=1000)
    for i in range(60):
        writer.add(record(i))
        writer.flush()
    paths = segments.segment_paths(tmp_path)
    assert sum(p.stat().st_size for p in paths) <= 3000
    kept = [r for s in segments.read_segments(paths, print) for r in s.records]
    assert kept[-1] == record(59) and kept == [record(i) for i in range(60 - len(kept), 60)]
    assert not [p for p in tmp_path.iterdir() if p.name.startswith(".")]  # no temporaries left


def test_a_new_writer_continues_the_numbering_and_the_power_on_count(tmp_path: Path) -> None:
    first = SegmentWriter(tmp_path, max_bytes=10**6)
    first.add(record(0, power_on=7))
    first.flush()
    assert segments.last_power_on(tmp_path, print) == 7
    second = SegmentWriter(tmp_path, max_bytes=10**6)
    second.add(record(1, power_on=8))
    second.flush()
    names = [p.name for p in segments.segment_paths(tmp_path)]
    assert names == ["field-00000000.jsonl", "field-00000001.jsonl"]
    assert segments.last_power_on(tmp_path / "none", print) is None
    lines: list[str] = []
    segments.segment_paths(tmp_path)[1].write_bytes(b"cut")
    assert segments.last_power_on(tmp_path, lines.append) == 7  # the newest is damaged: the one before
    assert len(lines) == 1 and "field-00000001.jsonl" in lines[0]


def test_segments_get_the_users_umask(tmp_path: Path) -> None:
    import os

    old = os.umask(0o027)
    try:
        writer = SegmentWriter(tmp_path, max_bytes=10**6)
        writer.add(record())
        writer.flush()
    finally:
        os.umask(old)
    assert segments.segment_paths(tmp_path)[0].stat().st_mode & 0o777 == 0o640


@pytest.mark.parametrize(("change", "field"), [
    ({"utc": datetime(2026, 1, 1)}, "utc"), ({"vehicle_id": ""}, "vehicle_id"), ({"set_id": -1}, "set_id"),
    ({"power_on": True}, "power_on"), ({"since_power_on_s": float("nan")}, "since_power_on_s"),
    ({"temp_c": float("inf")}, "temp_c"), ({"bias_dps": (0.1, 0.2)}, "bias_dps"),
    ({"sigma_dps": (-1.0,)}, "sigma_dps"), ({"decision": "maybe"}, "decision")])
def test_a_record_that_breaks_its_invariants_is_refused_naming_the_field(change: dict[str, object],
                                                                         field: str) -> None:
    with pytest.raises(RecordError, match=field):
        record(**change)


def test_a_power_on_record_has_no_temperature_and_reads_back() -> None:
    r = record(decision=POWER_ON, temp_c=None, since_power_on_s=0.0)
    assert FieldRecord.from_json(r.to_json()) == r


def _write_forever(directory: Path, first: int, ready: int) -> None:
    """The forked writer: records numbered from ``first``, one flush per record, until killed."""
    import os

    try:
        writer = SegmentWriter(directory, max_bytes=6000, segment_bytes=1500)
        os.write(ready, b"r")
        i = first
        while True:
            writer.add(record(i, power_on=i))
            writer.flush()
            i += 1
    finally:
        os._exit(0)


def test_a_writer_killed_at_random_moments_leaves_only_whole_segments(tmp_path: Path) -> None:
    """SIGKILL at 60 random moments while a writer flushes and rotates: every segment reads whole,
    the records are consecutive (the oldest rotated away), a restart continues after the last."""
    import os
    import random
    import signal
    import time

    rng = random.Random(7)
    last = -1
    for _trial in range(60):
        ready_r, ready_w = os.pipe()
        pid = os.fork()
        if pid == 0:
            os.close(ready_r)
            _write_forever(tmp_path, last + 1, ready_w)
        os.close(ready_w)
        assert os.read(ready_r, 1) == b"r"
        os.close(ready_r)
        time.sleep(rng.uniform(0.0, 0.02))
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        lines: list[str] = []
        numbers = [r.power_on for s in segments.read_segments(segments.segment_paths(tmp_path), lines.append)
                   for r in s.records]
        assert lines == []
        assert numbers == list(range(numbers[0], numbers[0] + len(numbers))) if numbers else last == -1
        if numbers:
            assert numbers[-1] >= last
            last = numbers[-1]
    assert last > 60  # the writer did write between the kills
    SegmentWriter(tmp_path, max_bytes=6000)
    assert not list(tmp_path.glob(".*.tmp"))  # a new writer removes what a kill left half-written
