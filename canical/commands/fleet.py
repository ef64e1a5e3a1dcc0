"""``canical fleet ingest|analyse``: the field logs of a fleet, collected and analysed.

``ingest DIR... -o DATASET`` adds the segments' records to a Parquet dataset (a folder per
vehicle and day; a record already there is not added again); ``analyse DATASET --report-dir R``
judges each sensor from its records (see :mod:`canical.fleet`), in process or on a Dask cluster.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

from canical.commands import COMMANDS
from canical.errors import CanicalError


def register(sub) -> None:
    p = sub.add_parser("fleet", help=COMMANDS["fleet"], description=__doc__.split("\n\n")[0])
    actions = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    ingest = actions.add_parser("ingest", help="add field-log segments to a Parquet dataset")
    ingest.add_argument("sources", nargs="+", metavar="DIR",
                        help="field-log folders (searched recursively for field-*.jsonl) or segment files")
    ingest.add_argument("-o", "--output", required=True, metavar="DATASET",
                        help="the dataset folder (made if missing; records already in it are kept once)")
    ingest.set_defaults(run=run_ingest)


def run_ingest(args: argparse.Namespace) -> int:
    from canical.files.output_plan import output_plan
    from canical.fleet.ingest import ingest

    target = Path(args.output)
    if target.exists() and not target.is_dir():
        raise CanicalError(f"{target}: not a folder (a dataset is a folder)")
    with output_plan(dirs=[target]):
        done = ingest([Path(s) for s in args.sources], target, lambda line: print(line, file=sys.stderr))
    print(f"fleet ingest: {done.segments} segments read ({done.skipped} damaged, skipped), {done.rows} rows: "
          f"{done.added} added to {target} in {done.partitions} partitions, "
          f"{done.rows - done.added} already there")
    return 0
