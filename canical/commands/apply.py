"""``canical apply``: add calibrated rates to a CSV of raw samples.

The output is the input, row for row and byte for byte, with ``rate_dps`` and
``out_of_span`` appended. Only the raw column (and the inputs the set's terms
name) are parsed; a reference column, if present, is never read.
"""

from __future__ import annotations

import argparse
import io
import re
from collections.abc import Callable
from typing import TYPE_CHECKING

from canical.commands import COMMANDS
from canical.commands.canlog_args import add_canlog_arguments
from canical.commands.trust_args import add_trust_argument, check_trusted
from canical.errors import CanicalError
from canical.files.output_plan import output_plan
from canical.progress import Progress
from canical.sessions.canlog_format import CANLOG_FORMATS

if TYPE_CHECKING:  # the rest is imported where used: `--help` needs none of it
    import numpy as np

    from canical.sessions.csv_chunks import CsvHead
    from canical.sets.coefficients import CoefficientSet
    from canical.sets.corrector import Corrector

CHUNK_ROWS = 100_000
#: ``--vehicle-id``'s default, and the ids it takes (the daemon's field_log.vehicle_id's rule).
DEFAULT_VEHICLE = "offline"
VEHICLE_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")


def register(sub) -> None:
    p = sub.add_parser("apply", help=COMMANDS["apply"])
    p.add_argument("coefficients", help="coefficient set YAML")
    p.add_argument("input",
                   help=f"CSV with a raw column, or a CAN log ({CANLOG_FORMATS}) with --dbc/--config")
    p.add_argument("-o", "--output", required=True, help="CSV to write (input + rate_dps, out_of_span)")
    p.add_argument("--raw-column", default="raw", help="column with the raw sensor output")
    p.add_argument("--sensor", help="sensor id of the input (default: its '# sensor:' line)")
    add_trust_argument(p, what=" (else the set is refused)")
    add_canlog_arguments(p)
    track = p.add_argument_group("bias tracking (learn the bias at standstills, append bias_dps)")
    track.add_argument("--track-bias", action="store_true",
                       help="replay the drive through the bias tracker row by row and append bias_dps "
                            "(subtract it from rate_dps); a CSV needs a time_s column (time since "
                            "power-on), a CAN log takes it from the time_s input if mapped; with "
                            "--config whose bias_tracking: is on, tracks with its settings, as the daemon")
    track.add_argument("--standstill-column", metavar="NAME",
                       help="cue column (vehicle speed, or a moving flag; in a CAN log an input mapped "
                            "with --input/--config): stopped while within ± --standstill-below (a signed "
                            "speed in reverse is moving); nothing is "
                            "learned while it says moving")
    track.add_argument("--standstill-below", type=float, default=0.1, metavar="X",
                       help="cue magnitude below which the vehicle stands (default 0.1)")
    track.add_argument("--temp-column", default="temp_c", metavar="NAME",
                       help="temperature column the bias is learned against (default temp_c, if present)")
    track.add_argument("--arw", type=float, metavar="DEG_PER_RT_H",
                       help="the sensor's angle random walk (default: the set's fit.arw_deg_rt_h, else 0.5)")
    track.add_argument("--report-dir", metavar="DIR",
                       help="write a drive report there: heading with and without tracking, learned "
                            "bias against temperature, each standstill used or refused and why")
    track.add_argument("--field-log", metavar="DIR",
                       help="write each standstill decision and power-on there as the daemon's field_log "
                            "does: one new segment, the power-on count continuing the folder's")
    track.add_argument("--vehicle-id", default=DEFAULT_VEHICLE, metavar="ID",
                       help=f"the vehicle id in the field records (default {DEFAULT_VEHICLE})")
    track.add_argument("--drive-start", metavar="UTC",
                       help="when the drive began, ISO 8601 (default: the input's modification time "
                            "less the drive's length): the records' UTC times")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    if (args.standstill_column or args.report_dir or args.arw is not None or args.field_log) \
            and not args.track_bias:
        raise CanicalError("--standstill-column, --report-dir, --arw and --field-log need --track-bias")
    if (args.vehicle_id != DEFAULT_VEHICLE or args.drive_start) and not args.field_log:
        raise CanicalError("--vehicle-id and --drive-start need --field-log")
    if not VEHICLE_ID.match(args.vehicle_id):
        raise CanicalError(f"--vehicle-id {args.vehicle_id!r}: 1-64 letters, digits, '.', '_' or '-'")
    check_trusted("apply", args.coefficients, args.trust)
    with output_plan(args.output, dirs=[args.report_dir, args.field_log]):
        return apply_set(args)


def apply_set(args: argparse.Namespace) -> int:
    from canical.sessions.canlog_format import is_canlog
    from canical.sessions.csv_chunks import read_head
    from canical.sets import coefficient_file
    from canical.sets.corrector import Corrector
    from canical.sets.imu_set import is_imu_set_file

    if is_imu_set_file(args.coefficients):  # three axes and their coupling: its own module
        from canical.commands.apply_imu import apply_imu_set

        return apply_imu_set(args)
    cset = coefficient_file.load(args.coefficients)
    corrector = Corrector(cset)
    if is_canlog(args.input):
        return run_canlog(args, corrector)
    # The drive report draws the whole drive: with --report-dir the file is read whole.
    whole = (args.track_bias and args.report_dir) or not corrector.elementwise_model
    head = None if whole else read_head(args.input)
    if head is None:
        return apply_table(args, corrector)
    return apply_stream(args, corrector, head)


def apply_table(args: argparse.Namespace, corrector: Corrector) -> int:
    """The whole file in memory: for the bias tracker's replay (it looks at the whole drive), a
    rate model whose result depends on the block (the forward polynomial's Newton), and a file
    whose head :func:`~canical.sessions.csv_chunks.read_head` leaves to ``read_table``."""
    import numpy as np

    from canical.sessions.csv_file import read_table

    cset = corrector.cset
    needed = [args.raw_column, *corrector.required_inputs]
    if args.track_bias:
        needed = list(dict.fromkeys([*needed, *tracking_columns(args.input, args)]))
    table = read_table(args.input, columns=needed)
    check_input(args, cset, table.meta, table.header)
    inputs = {name: table.columns[name] for name in corrector.required_inputs}
    rate, oos = corrector.correct(table.columns[args.raw_column], inputs)
    extra: dict[str, np.ndarray] = {}
    if args.track_bias:
        extra["bias_dps"] = track_bias(args, cset, table.columns, rate)
    write_rows(args.output, table, rate, oos, extra)
    print_applied(args, corrector, len(table.rows), int(np.count_nonzero(oos)))
    return 0


def apply_stream(args: argparse.Namespace, corrector: Corrector, head: CsvHead) -> int:
    """Read, correct and write block by block, in memory bounded by the block.

    The set's state (direction, slope, lag, derivative) is carried from block to block
    (``Corrector.correct_next``), and so is the bias tracker's with ``--track-bias``
    (:class:`~canical.tracking.replay.Replayer`), so the output is, byte for byte, what the
    whole file at once gives (:func:`apply_table`).
    """
    import os
    from concurrent.futures import Future, ThreadPoolExecutor
    from functools import partial

    import numpy as np

    from canical.files.atomic_file import atomic_writer
    from canical.sessions.csv_chunks import read_chunks
    from canical.sessions.fixed_cells import append_cells

    cset = corrector.cset
    check_input(args, cset, head.meta, head.header)
    columns = [args.raw_column, *corrector.required_inputs]
    replayer = None
    if args.track_bias:
        from canical.commands.track_bias import print_events, replayer_for, tracking_inputs, write_field_log

        columns = list(dict.fromkeys([*columns, *tracking_columns(args.input, args)]))
        replayer = replayer_for(args, [cset.fit], (cset.axis,))
    last_bias = np.full(1, np.nan)
    progress = Progress("apply", max(os.path.getsize(args.input) >> 20, 1), unit="MB")
    done = head.data_offset
    n_rows = n_out = 0
    # A block's text is made and written by a thread while the next block is read and
    # corrected (the text is made in numpy and written to a file, both letting go of the
    # interpreter, while reading holds it): the blocks' texts come out in order, the state
    # (set, tracker) stays on this thread. One block in the thread at most, so memory stays two
    # blocks and a failed write stops the run at the next block. Leaving the pool waits for
    # that block before the output is kept or discarded.
    with atomic_writer(args.output, "wb") as out, ThreadPoolExecutor(max_workers=1) as writer:
        pending: Future[int] | None = None

        def write(text: Callable[[], bytes | memoryview]) -> None:
            nonlocal pending
            if pending is not None:
                pending.result()
            pending = writer.submit(lambda: out.write(text()))

        preamble = "".join(line + "\n" for line in head.preamble).encode("utf-8")
        write(lambda: preamble)
        added = ["rate_dps", "out_of_span", *(["bias_dps"] if replayer is not None else [])]
        header = (",".join([*head.header, *added]) + "\n").encode("utf-8")
        write(lambda: header)
        for chunk in read_chunks(head, columns):
            inputs = {name: chunk.columns[name] for name in corrector.required_inputs}
            rate, oos = corrector.correct_next(chunk.columns[args.raw_column], inputs)
            extra = []
            if replayer is not None and chunk.n_rows:
                time_s, temp, cue = tracking_inputs(args, chunk.columns)
                extra = [replayer.feed(time_s, rate, temp, cue)[:, 0]]
                last_bias = extra[0][-1:]
            if chunk.text is not None:  # the cells here, the rows joined there: the work halved
                write(partial(append_cells, chunk.text, _cells(rate, oos, extra)))
            else:
                write(partial(_rows_text, chunk.rows or [], rate, oos, extra))
            n_rows += chunk.n_rows
            n_out += int(np.count_nonzero(oos))
            done += chunk.size
            progress.update(done >> 20)
        if pending is not None:
            pending.result()
        if replayer is not None:  # before the output is kept: the summary of what was learned
            finished = replayer.finish()
            print_events(finished, (cset.axis,), last_bias)
            write_field_log(args, finished, (cset.axis,), field_source(cset))
    print_applied(args, corrector, n_rows, n_out)
    return 0


def _cells(rate: np.ndarray, oos: np.ndarray, extra: list[np.ndarray]) -> list[np.ndarray]:
    """A plain block's new cells as rows of bytes, for :func:`append_cells` to place in its rows."""
    from canical.sessions.fixed_cells import fixed6_cells, flag_cells

    return [fixed6_cells(rate), flag_cells(oos), *(fixed6_cells(b) for b in extra)]


def _rows_text(rows: list[str], rate: np.ndarray, oos: np.ndarray, extra: list[np.ndarray]) -> bytes:
    """A block that is not plain: its rows formatted one by one."""
    return _chunk_text(rows, rate, oos, extra).encode("utf-8")


def check_input(args: argparse.Namespace, cset, meta: dict[str, str], header: list[str]) -> None:
    """The file is from the set's sensor and axis, and has none of the columns apply adds."""
    sensor = args.sensor or meta.get("sensor")
    if sensor and sensor != cset.sensor_id:
        raise CanicalError(
            f"{args.coefficients} is for sensor {cset.sensor_id}, {args.input} is from {sensor}"
        )
    axis = meta.get("axis")
    if axis and axis != cset.axis:
        raise CanicalError(f"{args.coefficients} is for axis {cset.axis}, {args.input} is axis {axis}")
    for name in ("rate_dps", "out_of_span", *(["bias_dps"] if args.track_bias else [])):
        if name in header:
            raise CanicalError(f"{args.input} already has a {name} column")


def print_applied(args: argparse.Namespace, corrector: Corrector, n_rows: int, n_out: int) -> None:
    note = f", {n_out} outside the calibrated span (flagged)" if n_out else ""
    print(f"apply: {n_rows} rows corrected with set 0x{corrector.set_id:08x}{note} -> {args.output}")


def write_rows(path: str, table, rate: np.ndarray, oos: np.ndarray,
               extra: dict[str, np.ndarray] | None = None) -> None:
    """Echo the input rows with the new columns, atomically, in chunks with progress."""
    from canical.files.atomic_file import atomic_writer

    extra = extra or {}
    progress = Progress("apply", len(table.rows))
    with atomic_writer(path) as out:
        for line in table.preamble:
            out.write(line + "\n")
        out.write(",".join([*table.header, "rate_dps", "out_of_span", *extra]) + "\n")
        for start in range(0, len(table.rows), CHUNK_ROWS):
            stop = min(start + CHUNK_ROWS, len(table.rows))
            out.write(_chunk_text(table.rows[start:stop], rate[start:stop], oos[start:stop],
                                  [col[start:stop] for col in extra.values()]))
            progress.update(stop)


def _chunk_text(rows: list[str], rate: np.ndarray, oos: np.ndarray, extra: list[np.ndarray]) -> str:
    """Rows with their new columns; the extra columns (the tracked bias) joined once per row only
    when there are any, so plain ``apply`` keeps its one format per row."""
    buf = io.StringIO()
    if not extra:
        for line, r, o in zip(rows, rate, oos, strict=True):
            buf.write(f"{line},{r:.6f},{int(o)}\n")
        return buf.getvalue()
    tails = ["".join(cells) for cells in zip(*([f",{v:.6f}" for v in col.tolist()] for col in extra),
                                            strict=True)]
    for line, r, o, tail in zip(rows, rate, oos, tails, strict=True):
        buf.write(f"{line},{r:.6f},{int(o)}{tail}\n")
    return buf.getvalue()


def tracking_columns(path: str, args: argparse.Namespace) -> list[str]:
    """time_s, the cue if asked for, and the temperature column if the file has one."""
    from canical.sessions.csv_chunks import read_header

    header = read_header(path)
    if "time_s" not in header:
        raise CanicalError(f"{path}: --track-bias needs a time_s column (time since power-on)")
    if args.standstill_column and args.standstill_column not in header:
        raise CanicalError(f"{path}: no column {args.standstill_column!r} for --standstill-column")
    return ["time_s", *([args.standstill_column] if args.standstill_column else []),
            *([args.temp_column] if args.temp_column in header else [])]


def track_bias(args: argparse.Namespace, cset, columns: dict[str, np.ndarray],
               rate: np.ndarray) -> np.ndarray:
    """The drive replayed through the tracker for the set's axis (:mod:`.track_bias`)."""
    from canical.commands.track_bias import tracked_bias

    bias: np.ndarray = tracked_bias(args, [cset.fit], (cset.axis,), columns, rate, field_source(cset))[:, 0]
    return bias


def field_source(cset) -> tuple[str, int]:
    """The sensor and set a drive's field records name: the set's sensor id and CRC (what the
    daemon names with this set alone)."""
    from canical.sets.coefficient_file import set_crc

    return cset.sensor_id, set_crc(cset)


def use_daemon_tracking(args: argparse.Namespace) -> None:
    """With --config whose bias_tracking: is on, track exactly as the daemon: its settings, cue and
    temperature inputs (what the command line gives of them is not used)."""
    if not args.config:
        return
    from canical.bus.daemon_config import load_config

    tracking = load_config(args.config).bias_tracking
    if tracking is None:
        return
    args.daemon_tracking = tracking.settings
    args.standstill_column = tracking.settings.cue_input
    args.temp_column = tracking.temperature_input or ""
    print(f"apply: bias tracking as configured in {args.config} (bias_tracking:)")


def run_canlog(args: argparse.Namespace, corrector: Corrector) -> int:
    """A CAN log, read as the daemon reads the bus: one row per raw frame of the set's axis.

    Writes time_s, raw, the inputs the set needs, rate_dps and out_of_span.
    """
    import numpy as np

    from canical.commands.canlog_args import canlog_source
    from canical.files.atomic_file import atomic_writer
    from canical.sessions.canlog import TIME_INPUT, read_canlog
    from canical.sessions.session import RAW_UNITS

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
    if args.track_bias:
        use_daemon_tracking(args)
        if args.standstill_column and args.standstill_column not in source.inputs:
            raise CanicalError(f"--standstill-column {args.standstill_column}: map it to a signal with "
                               f"--input {args.standstill_column}=MESSAGE.Signal or --config")
        extra = [n for n in ("time_s", args.standstill_column, args.temp_column) if n in source.inputs]
        needed = list(dict.fromkeys([*needed, *extra]))
    raw_signal = source.raw_signals.get(cset.axis)
    if corrector.elementwise_model and not args.track_bias:
        return _apply_canlog_stream(args, corrector, source, sensor, needed, raw_signal)
    log = read_canlog(
        args.input,
        dbc=source.dbc,
        axis=cset.axis,
        inputs=source.axis_inputs(cset.axis, needed),
        ref=None,
        raw_message=source.raw_message,
        raw_signal=raw_signal,
        sensor=sensor,
        j1939_source=source.j1939_source,
    )
    session = log.session
    refuse_other_units(args, cset, session.meta.get(RAW_UNITS))
    inputs = {n: session.aux[n] for n in session.aux}
    if TIME_INPUT in corrector.required_inputs:
        inputs[TIME_INPUT] = session.time_s
    rate, oos = corrector.correct(session.raw, inputs)
    tracked = []
    if args.track_bias:
        columns = {**session.aux, "time_s": session.time_s}
        tracked = [track_bias(args, cset, columns, rate)]
    names = ["time_s", "raw", *session.aux, "rate_dps", "out_of_span", *(["bias_dps"] if tracked else [])]
    with atomic_writer(args.output) as out:
        for key, value in session.meta.items():
            out.write(f"# {key}: {value}\n")
        out.write(",".join(names) + "\n")
        out.write(_canlog_rows(session.time_s, session.raw, list(session.aux.values()), rate, oos, tracked))
    _print_canlog_applied(args, corrector, source.raw_message, len(session), int(np.count_nonzero(oos)),
                          log.skipped)
    return 0


def refuse_other_units(args: argparse.Namespace, cset: CoefficientSet, signal_units: str | None) -> None:
    """A set made for raw values in another unit than the log's signal: one line, nothing written."""
    from canical.sets.admission import raw_units_problem

    problem = raw_units_problem(cset.raw_units, signal_units)
    if problem:
        raise CanicalError(f"{args.coefficients}: {problem}")


def _apply_canlog_stream(args: argparse.Namespace, corrector: Corrector, source, sensor: str | None,
                         needed: list[str], raw_signal: str | None) -> int:
    """A CAN log read, corrected and written a block of rows at a time (memory bounded by the
    block): the set's state carried from block to block, so the output is, byte for byte, the one
    the whole log at once gives (:func:`run_canlog` without ``--track-bias``)."""
    import numpy as np

    from canical.files.atomic_file import atomic_writer
    from canical.sessions.canlog import TIME_INPUT, stream_canlog
    from canical.sessions.session import RAW_UNITS

    cset = corrector.cset
    stream = stream_canlog(args.input, dbc=source.dbc, axis=cset.axis,
                           inputs=source.axis_inputs(cset.axis, needed), raw_message=source.raw_message,
                           raw_signal=raw_signal, sensor=sensor, j1939_source=source.j1939_source)
    refuse_other_units(args, cset, stream.meta.get(RAW_UNITS))
    n_rows = n_out = 0
    with atomic_writer(args.output) as out:
        for key, value in stream.meta.items():
            out.write(f"# {key}: {value}\n")
        out.write(",".join(["time_s", "raw", *stream.channels, "rate_dps", "out_of_span"]) + "\n")
        for block in stream.blocks():
            inputs = dict(block.aux)
            if TIME_INPUT in corrector.required_inputs:
                inputs[TIME_INPUT] = block.time_s
            rate, oos = corrector.correct_next(block.raw, inputs)
            out.write(_canlog_rows(block.time_s, block.raw, list(block.aux.values()), rate, oos, []))
            n_rows += len(block.raw)
            n_out += int(np.count_nonzero(oos))
    _print_canlog_applied(args, corrector, source.raw_message, n_rows, n_out, stream.skipped)
    return 0


def _canlog_rows(time_s: np.ndarray, raw: np.ndarray, aux: list[np.ndarray], rate: np.ndarray,
                 oos: np.ndarray, tracked: list[np.ndarray]) -> str:
    """A log's rows as CSV text: time, raw and inputs, then rate, out-of-span flag (and bias)."""
    import numpy as np

    buf = io.StringIO()
    fmt = ["%.6f", "%.9g"] + ["%.9g"] * len(aux)
    table = np.column_stack([time_s, raw, *aux, rate, oos.astype(float), *tracked])
    np.savetxt(buf, table, delimiter=",", fmt=[*fmt, "%.6f", "%d", *(["%.6f"] if tracked else [])])
    return buf.getvalue()


def _print_canlog_applied(args: argparse.Namespace, corrector: Corrector, raw_message: str, n_rows: int,
                          n_out: int, skipped: int) -> None:
    note = f", {n_out} outside the calibrated span (flagged)" if n_out else ""
    left_out = f"; {skipped} frames before the inputs' first values left out" if skipped else ""
    print(
        f"apply: {n_rows} {raw_message} frames (axis {corrector.cset.axis}) corrected with set "
        f"0x{corrector.set_id:08x}{note}{left_out} -> {args.output}"
    )
