"""Which drives ``fleet replay`` replays and with which sets: the drive files under the folders,
each one's vehicle (its folder's name) and sensor (its ``# sensor:`` line or Parquet metadata; a
CAN log's, ``--sensor`` or its configuration's),
and that sensor's baseline set and new set (its baseline again when no new set was proposed).

Why apart from :mod:`.replay`: this is the command's reading of folders, done once in the
command's process; the tasks it makes name files only, so they travel to workers as a few bytes.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path

from canical.errors import CanicalError
from canical.fleet.drive_log import LogLayout
from canical.fleet.proposal import SetSource, read_sets
from canical.fleet.replay import NEEDED, DriveTask, drive_sensor
from canical.sessions.canlog_format import is_canlog

DRIVE_SUFFIXES = (".csv", ".parquet")


def is_drive(path: Path) -> bool:
    """A drive file: a CSV, a Parquet file or a CAN log (by its suffix, under any ``.gz``)."""
    return path.suffix in DRIVE_SUFFIXES or is_canlog(path)


def drive_files(root: Path) -> list[Path]:
    if root.is_file():
        return [root]
    if not root.is_dir():
        raise CanicalError(f"{root}: no such drive file or folder")
    found = sorted(p for p in root.rglob("*") if p.is_file() and is_drive(p))
    if not found:
        raise CanicalError(f"{root}: no drives (*.csv, *.parquet, CAN logs)")
    return found


def by_sensor(sets: dict[tuple[str, str], SetSource], what: str) -> dict[str, SetSource]:
    out: dict[str, SetSource] = {}
    for (sensor, axis), source in sets.items():
        if sensor in out:
            raise CanicalError(f"{what}: sensor {sensor} has sets for two axes ({axis} in {source.path}); "
                               "fleet replay takes one axis per sensor")
        out[sensor] = source
    return out


def plan(drives: Path, new: Path, baseline: Path, note: Callable[[str], None],
         layout: LogLayout | None = None) -> list[DriveTask]:
    """A task per drive file, in path order (a CAN log read with ``layout``)."""
    old_sets = by_sensor(read_sets(baseline, note), f"--baseline {baseline}")
    new_sets = by_sensor(read_sets(new, note), f"--sets {new}")
    tasks = []
    for path in drive_files(drives):
        log = is_canlog(path)
        if log and layout is None:
            raise CanicalError(f"{path}: reading a CAN log needs --dbc or --config")
        sensor = drive_sensor(path, layout)
        if sensor is None:
            raise CanicalError(f"{path}: names no sensor (a CAN log's: --sensor or --config)" if log else
                               f"{path}: names no sensor (a '# sensor:' line, or Parquet metadata 'sensor')")
        if log and layout is not None:
            layout.check(path, NEEDED)
        if sensor not in old_sets:
            raise CanicalError(f"{path}: no baseline set for sensor {sensor} in {baseline}")
        old = old_sets[sensor]
        fresh = new_sets.get(sensor, old)
        vehicle = path.parent.name if path.parent != drives else path.stem
        tasks.append(DriveTask(str(path.resolve()), vehicle, sensor, str(old.path.resolve()),
                               str(fresh.path.resolve()), layout if log else None))
    return tasks
