"""``canical simulate fleet``: a simulated fleet's field logs, one folder per vehicle, and the truth.

Why a command: the fleet tools need a fleet to be tried on, and their tests a truth to be judged
against (:mod:`canical.sim.fleet`). ``-o DIR`` gets ``VEHICLE/field-NNNNNNNN.jsonl`` (segments as
the daemon writes them) and ``truth.csv``: one row per sensor with its lot, climate, planted
verdict, turn-on spread, temperature slope left by the set and drift per operating hour.
"""

from __future__ import annotations

import argparse
import csv
import dataclasses
import io
from pathlib import Path
from typing import TYPE_CHECKING

from canical.errors import CanicalError

if TYPE_CHECKING:
    from canical.sets.coefficients import CoefficientSet
    from canical.sim.fleet import SensorTruth

TRUTH = "truth.csv"


def check(args: argparse.Namespace) -> None:
    """The fleet's options: positive counts, an output folder that is new or empty."""
    if args.vehicles is None or args.days is None:
        raise CanicalError("simulate fleet: give --vehicles N and --days D")
    if not 1 <= args.vehicles <= 100_000 or not 1 <= args.days <= 3650:
        raise CanicalError("simulate fleet: --vehicles is 1..100000 and --days 1..3650")
    if (args.drives is None) != (args.drive_set is None) or not 0 < (args.drives or 1) <= 100:
        raise CanicalError("simulate fleet: --drives K (1..100) and --drive-set SET go together")
    out = Path(args.output)
    if out.exists() and (not out.is_dir() or any(out.iterdir())):
        raise CanicalError(f"{out}: not an empty folder (simulate fleet writes a folder per vehicle there)")


def run_fleet(args: argparse.Namespace) -> int:
    from canical.fieldlog.segments import pack, segment_name
    from canical.files.atomic_file import make_dirs, write_bytes_atomic, write_text_atomic
    from canical.files.output_plan import output_plan
    from canical.progress import Progress
    from canical.sim.fleet import simulate_vehicle

    check(args)
    out = Path(args.output)
    template = _drive_set(args.drive_set) if args.drive_set else None
    truths: list[SensorTruth] = []
    n_records = 0
    progress = Progress("simulate fleet", args.vehicles, unit="vehicles")
    with output_plan(dirs=[out]):
        make_dirs(out)
        for index in range(args.vehicles):
            truth, records = simulate_vehicle(index, args.days, args.seed)
            folder = out / truth.vehicle_id
            make_dirs(folder)
            for number, data in enumerate(pack(records)):
                write_bytes_atomic(folder / segment_name(number), data)
            truths.append(truth)
            n_records += len(records)
            if template is not None:
                write_drives(out, truth, index, args, template)
            progress.update(index + 1)
        write_text_atomic(out / TRUTH, truth_csv(truths))
    planted = {v: sum(t.verdict == v for t in truths) for v in ("drifting", "out of spec")}
    print(f"simulate: fleet of {args.vehicles} vehicles over {args.days} days: {n_records} records -> {out}")
    if template is not None:
        print(f"  {args.drives} raw drives per vehicle -> {out / 'drives'}; baseline sets -> {out / 'sets'}")
    print(f"  planted: {planted['drifting']} aging, {planted['out of spec']} failing sensors; "
          f"truth in {out / TRUTH}; seed {args.seed}")
    return 0


def truth_csv(truths: list) -> str:
    text = io.StringIO()
    fields = [f.name for f in dataclasses.fields(truths[0])]
    writer = csv.DictWriter(text, fieldnames=fields, lineterminator="\n")
    writer.writeheader()
    for truth in truths:
        writer.writerow(dataclasses.asdict(truth))
    return text.getvalue()


def _drive_set(path: str) -> CoefficientSet:
    """The baseline set every simulated sensor copies: segmented, without effect terms."""
    from canical.sets import coefficient_file

    cset = coefficient_file.load(path)
    if cset.terms or not cset.kind.piecewise:
        raise CanicalError(f"--drive-set {path}: a segmented set without effect terms (its rate model is "
                           "inverted to make the raw drives)")
    return cset


def write_drives(out: Path, truth: SensorTruth, index: int, args: argparse.Namespace,
                 template: CoefficientSet) -> None:
    """The vehicle's baseline set and its raw drives (with the truth: true_rate_dps)."""
    import numpy as np

    from canical.files.atomic_file import make_dirs, write_text_atomic
    from canical.sets import coefficient_file
    from canical.sim.fleet_drives import COLUMNS, drive_for, raw_of

    cset = dataclasses.replace(template, sensor_id=truth.sensor_id)
    coefficient_file.save(out / "sets" / f"{truth.sensor_id}.yaml", cset)
    folder = out / "drives" / truth.vehicle_id
    make_dirs(folder)
    for number in range(args.drives):
        drive = drive_for(truth, index, number, args.seed)
        table = np.column_stack([drive.time_s, raw_of(cset, drive.rate_dps), drive.temp_c, drive.speed_mps,
                                 drive.true_rate_dps])
        text = io.StringIO()
        text.write(f"# sensor: {truth.sensor_id}\n# vehicle: {truth.vehicle_id}\n{','.join(COLUMNS)}\n")
        np.savetxt(text, table, fmt=["%.2f", "%.3f", "%.2f", "%.3f", "%.5f"], delimiter=",")
        write_text_atomic(folder / f"drive-{number:03d}.csv", text.getvalue())
