"""``canical apply``: add calibrated rates to a CSV of raw samples.

The output is the input, row for row and byte for byte, with ``rate_dps`` and
``out_of_span`` appended. Only the raw column (and the inputs the set's terms
name) are parsed; a reference column, if present, is never read.
"""

from __future__ import annotations

import argparse
import io
from typing import TYPE_CHECKING

from canical.commands import COMMANDS
from canical.commands.canlog_args import add_canlog_arguments
from canical.errors import CanicalError
from canical.output_plan import output_plan
from canical.progress import Progress
from canical.sessions.canlog_format import CANLOG_FORMATS

if TYPE_CHECKING:  # the rest is imported where used: `--help` needs none of it
    import numpy as np

    from canical.sets.corrector import Corrector

CHUNK_ROWS = 100_000


def register(sub) -> None:
    p = sub.add_parser("apply", help=COMMANDS["apply"])
    p.add_argument("coefficients", help="coefficient set YAML")
    p.add_argument("input",
                   help=f"CSV with a raw column, or a CAN log ({CANLOG_FORMATS}) with --dbc/--config")
    p.add_argument("-o", "--output", required=True, help="CSV to write (input + rate_dps, out_of_span)")
    p.add_argument("--raw-column", default="raw", help="column with the raw sensor output")
    p.add_argument("--sensor", help="sensor id of the input (default: its '# sensor:' line)")
    add_canlog_arguments(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    with output_plan(args.output):
        return apply_set(args)


def apply_set(args: argparse.Namespace) -> int:
    import numpy as np

    from canical.sessions.canlog_format import is_canlog
    from canical.sessions.csv_file import read_table
    from canical.sets import coefficient_file
    from canical.sets.corrector import Corrector

    cset = coefficient_file.load(args.coefficients)
    corrector = Corrector(cset)
    if is_canlog(args.input):
        return run_canlog(args, corrector)
    needed = [args.raw_column, *corrector.required_inputs]
    table = read_table(args.input, columns=needed)
    sensor = args.sensor or table.meta.get("sensor")
    if sensor and sensor != cset.sensor_id:
        raise CanicalError(
            f"{args.coefficients} is for sensor {cset.sensor_id}, {args.input} is from {sensor}"
        )
    axis = table.meta.get("axis")
    if axis and axis != cset.axis:
        raise CanicalError(f"{args.coefficients} is for axis {cset.axis}, {args.input} is axis {axis}")
    for name in ("rate_dps", "out_of_span"):
        if name in table.header:
            raise CanicalError(f"{args.input} already has a {name} column")
    inputs = {name: table.columns[name] for name in corrector.required_inputs}
    rate, oos = corrector.correct(table.columns[args.raw_column], inputs)
    write_rows(args.output, table, rate, oos)
    n_out = int(np.count_nonzero(oos))
    note = f", {n_out} outside the calibrated span (flagged)" if n_out else ""
    print(f"apply: {len(table.rows)} rows corrected with set 0x{corrector.set_id:08x}{note} -> {args.output}")
    return 0


def write_rows(path: str, table, rate: np.ndarray, oos: np.ndarray) -> None:
    """Echo the input rows with the new columns, atomically, in chunks with progress."""
    from canical.atomic_file import atomic_writer

    progress = Progress("apply", len(table.rows))
    with atomic_writer(path) as out:
        for line in table.preamble:
            out.write(line + "\n")
        out.write(",".join([*table.header, "rate_dps", "out_of_span"]) + "\n")
        for start in range(0, len(table.rows), CHUNK_ROWS):
            stop = min(start + CHUNK_ROWS, len(table.rows))
            buf = io.StringIO()
            for line, r, o in zip(table.rows[start:stop], rate[start:stop], oos[start:stop], strict=True):
                buf.write(f"{line},{r:.6f},{int(o)}\n")
            out.write(buf.getvalue())
            progress.update(stop)


def run_canlog(args: argparse.Namespace, corrector: Corrector) -> int:
    """A CAN log, read as the daemon reads the bus: one row per raw frame of the set's axis.

    Writes time_s, raw, the inputs the set needs, rate_dps and out_of_span.
    """
    import numpy as np

    from canical.atomic_file import atomic_writer
    from canical.commands.canlog_args import canlog_source
    from canical.sessions.canlog import TIME_INPUT, read_canlog

    cset = corrector.cset
    source = canlog_source(args, args.input)
    sensor = args.sensor or source.sensor
    if sensor and sensor != cset.sensor_id:
        raise CanicalError(
            f"{args.coefficients} is for sensor {cset.sensor_id}, {args.input} is from {sensor}"
        )
    needed = list(corrector.required_inputs)  # time_s too: log time is not time since power-on
    unmapped = [n for n in needed if n not in source.inputs]
    if unmapped:
        raise CanicalError(
            f"the coefficient set needs input(s) {', '.join(unmapped)}: map them with "
            "--input NAME=MESSAGE.Signal or --config"
        )
    log = read_canlog(
        args.input,
        dbc=source.dbc,
        axis=cset.axis,
        inputs={n: source.inputs[n] for n in needed},
        ref=None,
        raw_message=source.raw_message,
        raw_signal=source.raw_signals.get(cset.axis),
        sensor=sensor,
    )
    session = log.session
    inputs = {n: session.aux[n] for n in session.aux}
    if TIME_INPUT in corrector.required_inputs:
        inputs[TIME_INPUT] = session.time_s
    rate, oos = corrector.correct(session.raw, inputs)
    names = ["time_s", "raw", *session.aux, "rate_dps", "out_of_span"]
    with atomic_writer(args.output) as out:
        for key, value in session.meta.items():
            out.write(f"# {key}: {value}\n")
        out.write(",".join(names) + "\n")
        buf = io.StringIO()
        cols = [session.time_s, session.raw, *session.aux.values()]
        fmt = ["%.6f", "%.9g"] + ["%.9g"] * len(session.aux)
        table = np.column_stack([*cols, rate, oos.astype(float)])
        np.savetxt(buf, table, delimiter=",", fmt=[*fmt, "%.6f", "%d"])
        out.write(buf.getvalue())
    n_out = int(np.count_nonzero(oos))
    note = f", {n_out} outside the calibrated span (flagged)" if n_out else ""
    skipped = f"; {log.skipped} frames before the inputs' first values left out" if log.skipped else ""
    print(
        f"apply: {len(session)} {source.raw_message} frames (axis {cset.axis}) corrected with set "
        f"0x{corrector.set_id:08x}{note}{skipped} -> {args.output}"
    )
    return 0
