"""The field log on disk: segments of JSON lines, each closed atomically with a CRC, rotated
within a size bound; read back with a damaged segment skipped in one line, never a traceback.

Why whole segments rewritten, not appended: a segment on disk is always complete (header, records,
a footer with the record count and a CRC of everything before it), so a power cut leaves the
last flushed segment or the one before, never a torn line, and a reader needs no recovery. A
segment holds at most :data:`SEGMENT_BYTES`, so a flush costs a few kilobytes; the daemon flushes
once per status period, so a cut loses at most the records since the last one. Only the standard
library and :mod:`canical.files.atomic_file`: the daemon pays nothing heavy for it.
"""

from __future__ import annotations

import json
import re
import zlib
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path

from canical.fieldlog.record import FIELDS, FieldRecord, RecordError
from canical.files.atomic_file import make_dirs, write_bytes_atomic

FORMAT = "canical-field-log"
VERSION = 1
#: A segment is closed (a new one started) once it holds this much.
SEGMENT_BYTES = 64 * 1024
#: A file larger than this is not a segment canical wrote: refused without reading it all.
MAX_SEGMENT_BYTES = 16 * 1024 * 1024
_NAME = re.compile(r"^field-(\d{8})\.jsonl$")


class SegmentError(ValueError):
    """A segment that cannot be used whole (damaged, truncated, foreign); the message says why."""


@dataclass(frozen=True)
class Segment:
    """One segment read back: where it is, its number and its records."""

    path: Path
    number: int
    records: tuple[FieldRecord, ...]


def segment_name(number: int) -> str:
    return f"field-{number:08d}.jsonl"


def encode(number: int, records: Iterable[FieldRecord]) -> bytes:
    """A segment's bytes: header, one record per line, footer with the count and the CRC."""
    lines = [json.dumps({"format": FORMAT, "version": VERSION, "segment": number, "fields": list(FIELDS)},
                        separators=(",", ":"))]
    lines += [json.dumps(r.to_json(), separators=(",", ":"), allow_nan=False) for r in records]
    body = ("\n".join(lines) + "\n").encode()
    footer = {"records": len(lines) - 1, "crc32": f"0x{zlib.crc32(body) & 0xFFFFFFFF:08x}"}
    return body + (json.dumps(footer, separators=(",", ":")) + "\n").encode()


def pack(records: Sequence[FieldRecord], first_number: int = 0,
         segment_bytes: int = SEGMENT_BYTES) -> list[bytes]:
    """Records as whole segments, each closed once it holds ``segment_bytes`` (as the writer closes
    them): for a writer that has all its records at once (a simulated fleet)."""
    out: list[bytes] = []
    start, size = 0, 0
    for i, record in enumerate(records):
        size += len(json.dumps(record.to_json(), separators=(",", ":"))) + 1
        if size >= segment_bytes or i == len(records) - 1:
            out.append(encode(first_number + len(out), records[start:i + 1]))
            start, size = i + 1, 0
    return out


def decode(data: bytes) -> tuple[int, tuple[FieldRecord, ...]]:
    """The segment number and records of a segment's bytes; :class:`SegmentError` if damaged."""
    body, _, footer_line = data.rstrip(b"\n").rpartition(b"\n")
    body += b"\n"
    try:
        footer = json.loads(footer_line)
        crc = int(footer["crc32"], 16)
        count = footer["records"]
    except (ValueError, KeyError, TypeError):
        raise SegmentError("no footer (truncated?)") from None
    if zlib.crc32(body) & 0xFFFFFFFF != crc:
        raise SegmentError("CRC mismatch (damaged)")
    lines = body.decode("utf-8", errors="replace").splitlines()
    try:
        header = json.loads(lines[0])
        if header.get("format") != FORMAT or header.get("version") != VERSION:
            raise SegmentError(f"not a {FORMAT} version {VERSION} segment")
        records = tuple(FieldRecord.from_json(json.loads(line)) for line in lines[1:])
    except (ValueError, AttributeError, IndexError) as exc:
        raise SegmentError(f"a bad line ({exc})") from None
    if len(records) != count:
        raise SegmentError(f"{len(records)} records, the footer says {count}")
    return int(header.get("segment", -1)), records


def read_segment(path: Path) -> Segment:
    """One segment file; :class:`SegmentError` naming why it cannot be used."""
    try:
        if path.stat().st_size > MAX_SEGMENT_BYTES:
            raise SegmentError(f"larger than {MAX_SEGMENT_BYTES // (1024 * 1024)} MiB")
        number, records = decode(path.read_bytes())
    except OSError as exc:
        raise SegmentError(f"cannot read ({exc.strerror or exc})") from None
    except RecordError as exc:
        raise SegmentError(str(exc)) from None
    return Segment(path, number, records)


def segment_paths(directory: Path) -> list[Path]:
    """A directory's segments, oldest first (by number)."""
    found = [p for p in directory.glob("field-*.jsonl") if _NAME.match(p.name)]
    return sorted(found, key=lambda p: p.name)


def read_segments(paths: Iterable[Path], warn: Callable[[str], None]) -> Iterator[Segment]:
    """Each usable segment; a damaged one is skipped with one line to ``warn`` naming it."""
    for path in paths:
        try:
            yield read_segment(path)
        except SegmentError as exc:
            warn(f"field log: skipped {path}: {exc}")


class SegmentWriter:
    """The field log of one vehicle in one directory: records buffered, flushed as whole segments.

    ``max_bytes`` bounds the directory's segments: after each flush the oldest are removed until
    the rest fit (the open segment is never removed).
    """

    def __init__(self, directory: Path, max_bytes: int, *, segment_bytes: int = SEGMENT_BYTES) -> None:
        self.directory = Path(directory)
        self.max_bytes = max_bytes
        self.segment_bytes = segment_bytes
        make_dirs(self.directory)
        for stale in self.directory.glob(".field-*.jsonl.*.tmp"):  # a write a power cut cut short
            stale.unlink(missing_ok=True)
        existing = segment_paths(self.directory)
        self.number = int(_NAME.match(existing[-1].name).group(1)) + 1 if existing else 0  # type: ignore[union-attr]
        self.open: list[FieldRecord] = []  # the open segment's records already on disk
        self.pending: list[FieldRecord] = []  # not yet on disk

    def add(self, record: FieldRecord) -> None:
        self.pending.append(record)

    def flush(self) -> None:
        """Write the open segment with the pending records (atomically), close it when full, rotate."""
        if not self.pending:
            return
        records = [*self.open, *self.pending]
        data = encode(self.number, records)
        write_bytes_atomic(self.directory / segment_name(self.number), data)
        self.pending.clear()
        if len(data) >= self.segment_bytes:
            self.number, self.open = self.number + 1, []
        else:
            self.open = records
        self.rotate()

    def rotate(self) -> None:
        """Remove the oldest segments until the directory's fit ``max_bytes`` (the open one stays)."""
        paths = segment_paths(self.directory)
        sizes = [p.stat().st_size for p in paths]
        total = sum(sizes)
        for path, size in zip(paths, sizes, strict=True):
            if total <= self.max_bytes or path.name == segment_name(self.number):
                break
            path.unlink(missing_ok=True)
            total -= size


def last_power_on(directory: Path, warn: Callable[[str], None]) -> int | None:
    """The highest power-on count in the directory's newest usable segment (None: no record); a
    damaged segment on the way is skipped with one line to ``warn``."""
    for path in reversed(segment_paths(Path(directory))):
        try:
            records = read_segment(path).records
        except SegmentError as exc:
            warn(f"field log: skipped {path}: {exc}")
            continue
        if records:
            return max(r.power_on for r in records)
    return None
