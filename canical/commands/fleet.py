"""``canical fleet ingest|analyse``: the field logs of a fleet, collected and analysed.

``ingest DIR... -o DATASET`` adds the segments' records to a Parquet dataset (a folder per
vehicle and day; a record already there is not added again); ``analyse DATASET --report-dir R``
judges each sensor from its records (see :mod:`canical.fleet`), in process or on a Dask cluster.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from canical.commands import COMMANDS
from canical.commands.canlog_args import add_canlog_arguments
from canical.errors import CanicalError

if TYPE_CHECKING:
    from canical.fleet.analysis import PowerOnSums, SensorVerdict
    from canical.fleet.drive_log import LogLayout
    from canical.fleet.proposal import SetSource
    from canical.fleet.replay import Generation

SetTable = dict[tuple[str, str], "SetSource"]


def register(sub) -> None:
    p = sub.add_parser("fleet", help=COMMANDS["fleet"], description=__doc__.split("\n\n")[0])
    actions = p.add_subparsers(dest="action", required=True, metavar="ACTION")
    ingest = actions.add_parser("ingest", help="add field-log segments to a Parquet dataset")
    ingest.add_argument("sources", nargs="+", metavar="DIR",
                        help="field-log folders (searched recursively for field-*.jsonl) or segment files")
    ingest.add_argument("-o", "--output", required=True, metavar="DATASET",
                        help="the dataset folder (made if missing; records already in it are kept once)")
    ingest.set_defaults(run=run_ingest)
    analyse = actions.add_parser("analyse",
                                 help="judge each sensor from a dataset: sensors.csv, report.md, plots")
    analyse.add_argument("dataset", metavar="DATASET", help="a dataset fleet ingest wrote")
    analyse.add_argument("--report-dir", required=True, metavar="R",
                         help="where sensors.csv, report.md and the plots go")
    analyse.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                         help="a Dask distributed scheduler to run on (default: in this process, no "
                              "cluster); its workers must see DATASET at the same path")
    analyse.add_argument("--lots", metavar="CSV",
                         help="a sensor table (columns sensor_id, lot) naming each sensor's lot (default: "
                              "the sensor id's prefix before its dash)")
    analyse.add_argument("--propose-sets", metavar="SETS",
                         help="the sensors' current sets (a folder of set files, or one): for each sensor "
                              "whose field temperature slope is significant, a new set with the "
                              "field-learned temperature term goes into -o NEW")
    analyse.add_argument("-o", "--output", metavar="NEW",
                         help="with --propose-sets: the folder for the new sets, proposals.md and "
                              "proposals.csv")
    analyse.set_defaults(run=run_analyse)
    replay = actions.add_parser("replay", help="replay raw drives with the baseline and the new sets: "
                                               "zero-rate error at standstills and heading drift")
    replay.add_argument("drives", metavar="DRIVES",
                        help="a folder of recorded raw drives (searched for *.csv, *.parquet and CAN logs; "
                             "a drive's vehicle is its folder's name, its sensor its '# sensor:' line, a "
                             "CAN log's --sensor) or one drive")
    replay.add_argument("--sets", required=True, metavar="NEW",
                        help="the new sets (a folder, as --propose-sets wrote it); a sensor without one "
                             "keeps its baseline")
    replay.add_argument("--baseline", required=True, metavar="OLD", help="the sets the drives ran with")
    replay.add_argument("--scheduler", metavar="tcp://HOST:PORT",
                        help="a Dask distributed scheduler to run on (default: in this process); its "
                             "workers must see the drives and sets at the same paths")
    replay.add_argument("-o", "--output", metavar="CSV",
                        help="write the per-vehicle figures there too (replay.csv)")
    replay.add_argument("--sensor",
                        help="the sensor id of the CAN logs (default: the configuration's sensor)")
    add_canlog_arguments(replay)
    replay.set_defaults(run=run_replay)


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


def run_analyse(args: argparse.Namespace) -> int:
    from canical.files.output_plan import output_plan
    from canical.fleet import engine, report
    from canical.fleet.analysis import DRIFTING, OUT_OF_SPEC, judge

    source = Path(args.dataset)
    if not source.is_dir():
        raise CanicalError(f"{source}: no such dataset folder")
    check_scheduler(args.scheduler)
    if (args.propose_sets is None) != (args.output is None):
        raise CanicalError("--propose-sets SETS and -o NEW go together")
    lots = report.read_lots(Path(args.lots)) if args.lots else report.Lots()
    sets = _read_sets(args.propose_sets)
    dirs = [args.report_dir] + ([args.output] if args.output else [])
    with output_plan(dirs=dirs):
        sums = engine.run(source, args.scheduler, print)
        verdicts = judge(sums)
        report.write(Path(args.report_dir), verdicts, str(source), lots)
        if sets is not None:
            _propose(verdicts, sums, sets, str(source), Path(args.output))
    flagged = {k: sum(v.verdict == k for v in verdicts) for k in (DRIFTING, OUT_OF_SPEC)}
    print(f"fleet analyse: {len(verdicts)} sensor axes: {flagged[OUT_OF_SPEC]} out of spec, "
          f"{flagged[DRIFTING]} drifting -> {Path(args.report_dir) / 'sensors.csv'}, report.md")
    return 0


def _read_sets(path: str | None) -> SetTable | None:
    """The sets given with --propose-sets (read before the analysis: a bad set fails fast)."""
    if path is None:
        return None
    from canical.fleet.proposal import read_sets

    return read_sets(Path(path), lambda line: print(line, file=sys.stderr))


def _propose(verdicts: list[SensorVerdict], sums: PowerOnSums, sets: SetTable, source: str,
             out: Path) -> None:
    """The new sets and proposals.md/csv in ``out``, a line per new set, and one to sign them."""
    from canical.fleet import proposal, proposal_files

    proposals = proposal.propose(verdicts, sums, sets, source)
    written = proposal_files.write(out, proposals)
    for p in proposals:
        if p.outcome == proposal.PROPOSED and p.evidence is not None:
            e = p.evidence
            print(f"proposed: {p.sensor_id} {p.axis}: field slope {e.slope_dps_per_c:+.5f} "
                  f"± {e.slope_se:.5f} deg/s/°C; standstill 1σ {e.before_dps:.4f} -> {e.after_dps:.4f} deg/s "
                  f"-> {out / proposal_files.set_name(p)}")
    unchanged = len(proposals) - len(written)
    print(f"fleet analyse: {len(written)} new sets, {unchanged} sensor axes unchanged "
          f"-> {out / 'proposals.md'}")
    signed = [p for p in proposals if p.outcome == proposal.PROPOSED and p.source and p.source.signed]
    if signed:
        print(f"fleet analyse: {len(signed)} of the old sets were signed and the new ones are not: sign each "
              f"before pushing (canical sign {out}/SET.yaml --key NAME.key)")


def check_scheduler(scheduler: str | None) -> None:
    if scheduler is not None and not scheduler.startswith(("tcp://", "tls://", "inproc://")):
        raise CanicalError(f"--scheduler {scheduler}: give the scheduler's address, tcp://HOST:PORT")


def log_layout(args: argparse.Namespace) -> LogLayout | None:
    """How CAN logs among the drives are read (``--dbc``/``--config``/``--input``, as ``apply``
    reads a log); None when neither a DBC nor a configuration is given."""
    from canical.commands.canlog_args import canlog_source
    from canical.fleet.drive_log import LogLayout

    if not (args.dbc or args.config):
        return None
    source = canlog_source(args, args.drives)
    return LogLayout(source.dbc, tuple(source.inputs.items()), source.raw_message,
                     tuple(source.raw_signals.items()), source.j1939_source, args.sensor or source.sensor)


def _less_noise(g: Generation) -> str:
    """The carried error less the standstills' own noise, with its 1σ (+: its upper bound)."""
    return f"{g.carried_less_noise_dps:.5f} (+{g.carried_less_noise_sd_dps:.5f})"


def run_replay(args: argparse.Namespace) -> int:
    from canical.files.atomic_file import write_text_atomic
    from canical.fleet import engine, replay, replay_plan

    check_scheduler(args.scheduler)
    tasks = replay_plan.plan(Path(args.drives), Path(args.sets), Path(args.baseline),
                             lambda line: print(line, file=sys.stderr), log_layout(args))
    results = engine.run_tasks(replay.replay_drive, tasks, args.scheduler, print, "fleet replay", "drives")
    vehicles = replay.per_vehicle(results)
    text = replay.vehicles_csv(vehicles)
    for v in vehicles:
        print(f"{v.vehicle_id} {v.sensor_id}: zero-rate error carried into {v.after.stops} standstills "
              f"{v.before.carried_rms_dps:.5f} -> {v.after.carried_rms_dps:.5f} deg/s, less their own noise "
              f"{_less_noise(v.before)} -> {_less_noise(v.after)} (with the tracked bias "
              f"{v.before.zero_rate_rms_dps:.5f} -> {v.after.zero_rate_rms_dps:.5f}); heading drift "
              f"{v.before.heading_rms_deg:.3f} -> {v.after.heading_rms_deg:.3f} deg")
    if args.output:
        write_text_atomic(args.output, text)
    rows = sum(v.rows for v in vehicles)
    print(f"fleet replay: {len(tasks)} drives, {rows} rows, {len(vehicles)} vehicles"
          + (f" -> {args.output}" if args.output else ""))
    return 0
