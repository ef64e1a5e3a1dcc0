"""``canical noise``: Allan deviation of a static record and the IEEE 952 terms read from it.

numpy, scipy, matplotlib and allantools are imported in ``run``, so ``--help`` stays fast.
"""

from __future__ import annotations

import argparse
import json
import sys

from canical.commands import COMMANDS
from canical.commands.canlog_args import add_canlog_arguments
from canical.errors import CanicalError

RATE_COLUMN = "rate_dps"
CORRECT_BLOCK = 1 << 20  # samples corrected at a time
DESCRIPTION = (
    "Angle random walk (deg/sqrt(h)), bias instability (deg/h) and rate random walk (deg/h/sqrt(h)) "
    "of a static record, with their intervals, from its Allan deviation (IEEE Std 952); a term the "
    "record is too short to show is reported as not resolved. Record the sensor at rest, as long as "
    "possible: rate random walk shows only past the crossover, often beyond ten minutes. The rate comes "
    "from a column in deg/s (rate_dps, as 'canical apply' writes it, or --column) or from the raw "
    "counts through a coefficient set (--coefficients); a CAN log needs the set (its axis and model) "
    "and --dbc or --config."
)


def register(sub) -> None:
    p = sub.add_parser("noise", help=COMMANDS["noise"], description=DESCRIPTION)
    p.add_argument("record", help="static record: CSV with time_s and a rate or raw column, or a CAN log")
    p.add_argument("--column", help=f"rate column in deg/s [{RATE_COLUMN}]")
    p.add_argument("--coefficients", help="coefficient set: convert the raw column (or the log's raw frames)")
    p.add_argument("--raw-column", default="raw", help="raw column, with --coefficients [raw]")
    p.add_argument("--plot", help="log-log Allan deviation plot to write (PNG)")
    p.add_argument("--json", help="the analysis (terms, intervals, curve) as JSON to write")
    add_canlog_arguments(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from canical.files.output_plan import output_plan

    with output_plan(args.plot, args.json):
        return characterise(args)


def characterise(args: argparse.Namespace) -> int:
    from canical.calibrate.allan import NoiseSkipped
    from canical.calibrate.noise_records import (
        AT_REST_SPAN_DPS,
        describe,
        first_backwards,
        motion_span_dps,
        noise_analysis,
        sample_interval,
        uniform_records,
    )
    from canical.sessions.canlog_format import is_canlog

    time_s, rate, where = _read_canlog(args) if is_canlog(args.record) else _read_csv(args)
    bad = first_backwards(time_s)
    if bad is not None:
        raise CanicalError(f"{args.record}: {where(bad)}: time goes backwards "
                           f"({time_s[bad - 1]:.6f} -> {time_s[bad]:.6f} s)")
    dt = sample_interval(time_s)
    span = motion_span_dps(time_s, rate)
    if span > AT_REST_SPAN_DPS:
        print(f"noise: warning: {args.record} is not at rest: its 1 s means span {span:.3g} deg/s "
              f"(at rest they stay within {AT_REST_SPAN_DPS:g}): the terms below describe the motion, "
              "not the sensor's noise", file=sys.stderr)
    records = uniform_records(time_s, rate, dt)
    del time_s, rate  # the records are views of the rate; the times' memory goes to the Allan sums
    analysis = noise_analysis(records, dt, str(args.record))
    if isinstance(analysis, NoiseSkipped):
        raise CanicalError(f"{args.record}: {analysis.skipped}")
    text = json.dumps(analysis.to_dict(), indent=2) + "\n"
    if args.plot:
        from canical.report.allan_plot import write_allan_plot

        write_allan_plot(analysis, args.plot, f"Allan deviation, {args.record}")
    if args.json:
        from canical.files.atomic_file import write_text_atomic

        write_text_atomic(args.json, text)
    print("\n".join(describe(analysis)))
    return 0


def _read_csv(args: argparse.Namespace):
    """time_s and the rate of a CSV, its columns read block by block; rows are named by their
    line in the file."""
    from canical.sessions.csv_chunks import read_columns, read_header
    from canical.sessions.csv_file import TIME_COLUMN

    on_block = _reading_progress(args.record)
    if args.coefficients:
        corrector = _corrector(args.coefficients)
        inputs = [n for n in corrector.required_inputs if n != TIME_COLUMN]
        needed = [TIME_COLUMN, args.raw_column, *inputs]

        def correct(columns):  # each block's raw counts to rates as read: the counts are not kept
            values = {n: columns[n] for n in inputs} | {TIME_COLUMN: columns[TIME_COLUMN]}
            return {TIME_COLUMN: columns[TIME_COLUMN],
                    RATE_COLUMN: _corrected(corrector, columns[args.raw_column], values)}

        if corrector.elementwise_model:
            table = read_columns(args.record, needed, on_block, convert=correct)
        else:  # the forward polynomial's Newton: the whole record at once
            table = read_columns(args.record, needed, on_block)
            table.columns.update(correct(table.columns))
        rate = table.columns[RATE_COLUMN]
    else:
        column = args.column or RATE_COLUMN
        if column not in read_header(args.record):
            raise CanicalError(f"{args.record}: no {column} column: name the rate column (deg/s) with "
                               "--column, or convert the raw column with --coefficients SET.yaml")
        table = read_columns(args.record, [TIME_COLUMN, column], on_block)
        rate = table.columns[column]
    first = table.first_data_line  # not the table: its raw column would stay in memory
    return table.columns[TIME_COLUMN], rate, lambda i: f"line {first + i}"


def _reading_progress(path: str):
    """Reading a long record takes a while: a progress line in MB read."""
    import os

    from canical.progress import Progress

    try:
        size = os.path.getsize(path)
    except OSError:  # the reader says what is wrong with it
        size = 0
    progress = Progress("noise: reading", max(size >> 20, 1), unit="MB")
    return lambda done: progress.update(done >> 20)


def _read_canlog(args: argparse.Namespace):
    """Frame times and the rate of the set's axis from a CAN log; rows are raw frames."""
    from canical.commands.canlog_args import canlog_source
    from canical.sessions.canlog import TIME_INPUT, read_canlog

    if not args.coefficients:
        raise CanicalError(f"{args.record}: a CAN log holds raw counts: give --coefficients SET.yaml")
    corrector = _corrector(args.coefficients)
    source = canlog_source(args, args.record)
    unmapped = [n for n in corrector.required_inputs if n not in source.inputs]
    if unmapped:
        raise CanicalError(f"the coefficient set needs input(s) {', '.join(unmapped)}: map them with "
                           "--input NAME=MESSAGE.Signal or --config")
    log = read_canlog(args.record, dbc=source.dbc, axis=corrector.cset.axis,
                      inputs=source.axis_inputs(corrector.cset.axis, corrector.required_inputs), ref=None,
                      raw_message=source.raw_message, raw_signal=source.raw_signals.get(corrector.cset.axis),
                      j1939_source=source.j1939_source)
    s = log.session
    inputs = dict(s.aux) | ({TIME_INPUT: s.time_s} if TIME_INPUT in corrector.required_inputs else {})
    rate = _corrected(corrector, s.raw, inputs)
    return s.time_s, rate, lambda i: f"{source.raw_message} frame {i + 1}"


def _corrected(corrector, raw, inputs):
    """The rate of a long record (or the next block of one), corrected a block at a time so that
    the model's temporaries stay small (the same values: a piecewise model evaluates each sample
    on its own, and the terms' state is carried from block to block)."""
    import numpy as np

    if not corrector.elementwise_model:
        return corrector.correct(raw, inputs)[0]
    rate = np.empty(len(raw))
    for a in range(0, len(raw), CORRECT_BLOCK):
        b = a + CORRECT_BLOCK
        rate[a:b] = corrector.correct_next(raw[a:b], {k: v[a:b] for k, v in inputs.items()})[0]
    return rate


def _corrector(path: str):
    from canical.sets import coefficient_file
    from canical.sets.corrector import Corrector

    return Corrector(coefficient_file.load(path))
