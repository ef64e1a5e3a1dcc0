"""A replay worker retains nothing per drive: replaying 4N drives in one process leaves no more
memory held than replaying N did (issue 35: bounded memory per worker).

Why: a worker holds one block of a drive at a time and returns only the drive's figures
(:class:`~canical.fleet.replay.DriveResult`, dropped here); a per-row array kept, a cache keyed
by drive or by set, a corrector or tracker kept from one drive to the next would show as traced
memory growing with the drives. ``tracemalloc`` sees Python's and numpy's allocations; pyarrow's
pool is read apart.
"""

from __future__ import annotations

import gc
import tracemalloc
from pathlib import Path

import pyarrow as pa
from support.parquet_drives import write_drive

from canical.fleet.replay import DriveTask, replay_drive

N = 4
ROWS = 4096  # a block of 32 KiB per column: one kept per drive would be seen at once
PER_DRIVE_BYTES = 1024  # retained per drive at most (none is expected)


def tasks(root: Path) -> list[DriveTask]:
    """Two drives of two vehicles, each with its sensor's set as both generations."""
    (root / "sets").mkdir()
    out = []
    for vehicle in (0, 1):
        path = root / f"drive-{vehicle}.parquet"
        made = write_drive(path, root / "sets", vehicle, 0, ROWS)
        sets = str(made.set_path)
        out.append(DriveTask(str(path), f"veh-{vehicle}", made.sensor_id, sets, sets))
    return out


def held_after(work: list[DriveTask], drives: int) -> tuple[int, int]:
    """Traced and pyarrow bytes held after replaying ``drives`` drives, results dropped."""
    for k in range(drives):
        replay_drive(work[k % len(work)])
    gc.collect()
    return tracemalloc.get_traced_memory()[0], pa.total_allocated_bytes()


def test_replaying_more_drives_holds_no_more_memory(tmp_path: Path) -> None:
    work = tasks(tmp_path)
    held_after(work, N)  # first calls: imports, module caches
    tracemalloc.start()
    try:
        traced_n, arrow_n = held_after(work, N)
        traced_4n, arrow_4n = held_after(work, 3 * N)
    finally:
        tracemalloc.stop()
    assert traced_4n - traced_n < 3 * N * PER_DRIVE_BYTES
    assert arrow_4n <= arrow_n
