"""``canical fleet ingest``: field-log segments of many vehicles into the Parquet dataset.

Why record by record against what is there: vehicles upload what they still hold, so the same
segment (or a later version of it, with more records) arrives again; each record's id is checked
against its partition's, and only new ones are added, as a new part file. A damaged segment is
skipped with one line naming it; the rest are ingested.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass
from pathlib import Path

from canical.errors import CanicalError
from canical.fieldlog import segments
from canical.files.atomic_file import make_dirs
from canical.fleet import dataset
from canical.progress import Progress


@dataclass(frozen=True)
class Ingested:
    """What one ingest did."""

    segments: int  # read whole
    skipped: int  # damaged, skipped
    rows: int  # rows read (a record per axis)
    added: int  # rows new to the dataset
    partitions: int  # folders a part file was added to


def find_segments(sources: Iterable[Path]) -> list[Path]:
    """The segments under each source: a segment file itself, or a folder searched recursively."""
    out: list[Path] = []
    for source in sources:
        if source.is_dir():
            out += sorted(p for p in source.rglob("field-*.jsonl"))
        elif source.is_file():
            out.append(source)
        else:
            raise CanicalError(f"{source}: no such file or folder")
    return out


def ingest(sources: Iterable[Path], target: Path, warn: Callable[[str], None]) -> Ingested:
    """Add every new record of the sources' segments to the dataset at ``target``."""
    paths = find_segments(sources)
    progress = Progress("fleet ingest", max(len(paths), 1), unit="segments")
    pending: dict[Path, list[dict[str, object]]] = {}
    read = skipped = 0
    for done, path in enumerate(paths, 1):
        try:
            segment = segments.read_segment(path)
        except segments.SegmentError as exc:
            warn(f"fleet ingest: skipped {path}: {exc}")
            skipped += 1
            continue
        read += 1
        for key, new in dataset.rows(segment.records).items():
            pending.setdefault(key, []).extend(new)
        progress.update(done)
    return _write(target, pending, read, skipped)


def _write(target: Path, pending: dict[Path, list[dict[str, object]]], read: int, skipped: int) -> Ingested:
    n_rows = added = touched = 0
    for key in sorted(pending):
        folder = target / key
        seen = dataset.ids_in(folder)
        fresh = []
        for row in pending[key]:
            n_rows += 1
            ident = (str(row["record_id"]), str(row["axis"]))
            if ident not in seen:
                seen.add(ident)
                fresh.append(row)
        if fresh:
            make_dirs(folder)
            dataset.write_part(folder, fresh)
            added += len(fresh)
            touched += 1
    return Ingested(read, skipped, n_rows, added, touched)
