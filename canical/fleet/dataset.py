"""The fleet dataset: field records as Parquet, one folder per vehicle and day, each record once.

Why this layout: a fleet adds a day of records per vehicle at a time, and the analysis reads a
sensor's records (its vehicle's folders) together; a folder per vehicle and day keeps both to a
few files. Why an id per record: the same segment is collected again (a vehicle uploads what it
still holds), so each row carries ``record_id`` (a hash of the record's content) and a record
already in its folder is never added twice. Part files are written whole and atomically.
"""

from __future__ import annotations

import hashlib
import io
import json
from collections.abc import Iterable, Sequence
from pathlib import Path
from urllib.parse import quote

import pyarrow as pa
import pyarrow.parquet as pq

from canical.fieldlog.record import FieldRecord
from canical.files.atomic_file import write_bytes_atomic

SCHEMA = pa.schema([
    ("utc", pa.timestamp("us", tz="UTC")), ("vehicle_id", pa.string()), ("sensor_id", pa.string()),
    ("set_id", pa.int64()), ("power_on", pa.int64()), ("since_power_on_s", pa.float64()),
    ("temp_c", pa.float64()), ("axis", pa.string()), ("bias_dps", pa.float64()), ("sigma_dps", pa.float64()),
    ("decision", pa.string()), ("reason", pa.string()), ("record_id", pa.string()),
])


def record_id(record: FieldRecord) -> str:
    """The record's identity: a hash of its content (the same record ingested twice, one id)."""
    text = json.dumps(record.to_json(), sort_keys=True, separators=(",", ":"))
    return hashlib.sha256(text.encode()).hexdigest()[:32]


def partition(vehicle_id: str, day: str) -> Path:
    """The folder of one vehicle's day, relative to the dataset (the id quoted: any text is safe)."""
    return Path(f"vehicle={quote(vehicle_id, safe='')}") / f"day={day}"


def rows(records: Iterable[FieldRecord]) -> dict[Path, list[dict[str, object]]]:
    """The records as rows (one per axis), grouped by their partition."""
    out: dict[Path, list[dict[str, object]]] = {}
    for r in records:
        rid = record_id(r)
        key = partition(r.vehicle_id, r.utc.strftime("%Y-%m-%d"))
        for axis, bias, sigma in zip(r.axes, r.bias_dps, r.sigma_dps, strict=True):
            out.setdefault(key, []).append({
                "utc": r.utc, "vehicle_id": r.vehicle_id, "sensor_id": r.sensor_id, "set_id": r.set_id,
                "power_on": r.power_on, "since_power_on_s": r.since_power_on_s, "temp_c": r.temp_c,
                "axis": axis, "bias_dps": bias, "sigma_dps": sigma, "decision": r.decision,
                "reason": r.reason, "record_id": rid})
    return out


def part_files(folder: Path) -> list[Path]:
    return sorted(folder.glob("part-*.parquet"))


def vehicle_folders(dataset: Path) -> list[Path]:
    """Each vehicle's folder of the dataset, in name order."""
    return sorted(p for p in dataset.glob("vehicle=*") if p.is_dir())


def ids_in(folder: Path) -> set[tuple[str, str]]:
    """The (record id, axis) pairs already in a partition's part files."""
    found: set[tuple[str, str]] = set()
    for path in part_files(folder):
        table = pq.read_table(path, columns=["record_id", "axis"])
        found.update(zip(table.column("record_id").to_pylist(), table.column("axis").to_pylist(),
                         strict=True))
    return found


def write_part(folder: Path, new_rows: Sequence[dict[str, object]]) -> Path:
    """New rows as one part file, named by its content, written atomically."""
    table = pa.Table.from_pylist(list(new_rows), schema=SCHEMA)
    digest = hashlib.sha256("".join(sorted(f"{r['record_id']}{r['axis']}" for r in new_rows)).encode())
    path = folder / f"part-{digest.hexdigest()[:20]}.parquet"
    buffer = io.BytesIO()
    pq.write_table(table, buffer, compression="zstd")
    write_bytes_atomic(path, buffer.getvalue())
    return path


def read_vehicle(folder: Path) -> pa.Table:
    """All of one vehicle's rows (every day's part files; one read of the folder, a quarter faster
    than file by file: most of a vehicle's time is opening its small files)."""
    if not any(folder.glob("day=*/part-*.parquet")):
        return SCHEMA.empty_table()
    return pq.read_table(folder, schema=SCHEMA, partitioning=None)
