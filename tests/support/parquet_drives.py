"""A simulated raw drive written as a Parquet file ``fleet replay`` reads, with its sensor's set.

Why one writer: ``bench_fleet.py`` replays many of them for the replay's cost and
``tests/fleet/test_replay_memory.py`` replays a few, many times, for what a worker retains.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass
from pathlib import Path

import pyarrow as pa
import pyarrow.parquet as pq

from canical.sets import coefficient_file
from canical.sim.fleet import simulate_vehicle
from canical.sim.fleet_drives import COLUMNS, drive_for, raw_of
from support.replay_fleets import SET


@dataclass(frozen=True)
class Written:
    """A drive written: its sensor, that sensor's set file and the drive's rows."""

    sensor_id: str
    set_path: Path
    rows: int


def write_drive(path: Path, sets: Path, vehicle: int, number: int, rows: int | None = None) -> Written:
    """Vehicle ``vehicle``'s drive ``number`` (its first ``rows`` rows) at ``path``, and its
    sensor's set (:data:`SET` under the sensor's id) in the folder ``sets``."""
    truth, _ = simulate_vehicle(vehicle, 1)
    sensor = dataclasses.replace(coefficient_file.load(SET), sensor_id=truth.sensor_id)
    set_path = sets / f"{truth.sensor_id}.yaml"
    coefficient_file.save(set_path, sensor)
    drive = drive_for(truth, vehicle, number)
    values = [drive.time_s, raw_of(sensor, drive.rate_dps), drive.temp_c, drive.speed_mps,
              drive.true_rate_dps]
    table = pa.table(dict(zip(COLUMNS, values, strict=True)))
    table = table.slice(0, rows) if rows is not None else table
    pq.write_table(table.replace_schema_metadata({"sensor": truth.sensor_id}), path)
    return Written(truth.sensor_id, set_path, table.num_rows)
