"""``canical apply imu.yaml drive.csv -o out.csv``: an IMU set on a CSV of the three raw outputs.

Reached from :mod:`canical.commands.apply` when the set file is an IMU set. The output is the
input, row for row and byte for byte, with ``rate_x_dps``, ``rate_y_dps``, ``rate_z_dps`` and
``out_of_span_x``, ``out_of_span_y``, ``out_of_span_z`` appended, and with ``--track-bias``
``bias_x_dps``, ``bias_y_dps``, ``bias_z_dps`` (one tracker over the three axes: a standstill
is the vehicle's). Only the raw columns (and the inputs the axes' terms name, and the tracking's
columns) are parsed.
"""

from __future__ import annotations

import argparse
import io

from canical.errors import CanicalError
from canical.progress import Progress

AXES = ("x", "y", "z")
RATE_COLUMNS = tuple(f"rate_{a}_dps" for a in AXES)
FLAG_COLUMNS = tuple(f"out_of_span_{a}" for a in AXES)
BIAS_COLUMNS = tuple(f"bias_{a}_dps" for a in AXES)
CHUNK_ROWS = 100_000


def apply_imu_set(args: argparse.Namespace) -> int:
    """Correct the three raw columns of a CSV with an IMU set (the output plan is the caller's)."""
    import numpy as np

    from canical.sessions.canlog_format import is_canlog
    from canical.sessions.csv_file import read_table
    from canical.sessions.triad_session import RAW_COLUMNS
    from canical.sets import imu_set
    from canical.sets.imu_corrector import ImuCorrector

    imu = imu_set.load(args.coefficients)
    corrector = ImuCorrector(imu)
    if is_canlog(args.input):
        return apply_imu_canlog(args, corrector)
    needed = [*RAW_COLUMNS, *corrector.required_inputs]
    if args.track_bias:
        from canical.commands.apply import tracking_columns

        needed = list(dict.fromkeys([*needed, *tracking_columns(args.input, args)]))
    table = read_table(args.input, columns=needed)
    sensor = args.sensor or table.meta.get("sensor")
    if sensor and sensor != imu.sensor_id:
        raise CanicalError(f"{args.coefficients} is for sensor {imu.sensor_id}, {args.input} is from "
                           f"{sensor}")
    for name in (*RATE_COLUMNS, *FLAG_COLUMNS, *(BIAS_COLUMNS if args.track_bias else ())):
        if name in table.header:
            raise CanicalError(f"{args.input} already has a {name} column")
    raw = np.column_stack([table.columns[c] for c in RAW_COLUMNS])
    rates, flags = corrector.correct(raw, {n: table.columns[n] for n in corrector.required_inputs})
    bias = None
    if args.track_bias:
        from canical.commands.track_bias import tracked_bias

        bias = tracked_bias(args, [c.fit for c in imu.axes], AXES, table.columns, rates, imu_source(imu))
    write_rows(args.output, table, rates, flags, bias)
    n_out = int(np.count_nonzero(flags.any(axis=1)))
    note = f", {n_out} with an axis outside its calibrated span (flagged)" if n_out else ""
    print(f"apply: {len(table.rows)} rows corrected with IMU set 0x{corrector.set_id:08x}{note} "
          f"-> {args.output}")
    return 0


def imu_source(imu) -> tuple[str, int]:
    """The sensor and set an IMU set's field records name: its sensor id and its own CRC."""
    from canical.sets.imu_set import imu_set_crc

    return imu.sensor_id, imu_set_crc(imu)


def write_rows(path: str, table, rates, flags, bias=None) -> None:
    """Echo the input rows with the six new columns (nine with the tracked bias), atomically, in
    chunks with progress."""
    from canical.files.atomic_file import atomic_writer

    progress = Progress("apply", len(table.rows))
    with atomic_writer(path) as out:
        for line in table.preamble:
            out.write(line + "\n")
        out.write(",".join([*table.header, *RATE_COLUMNS, *FLAG_COLUMNS,
                            *(BIAS_COLUMNS if bias is not None else ())]) + "\n")
        for start in range(0, len(table.rows), CHUNK_ROWS):
            stop = min(start + CHUNK_ROWS, len(table.rows))
            buf = io.StringIO()
            tails = ([f",{b[0]:.6f},{b[1]:.6f},{b[2]:.6f}" for b in bias[start:stop].tolist()]
                     if bias is not None else [""] * (stop - start))
            for line, r, f, tail in zip(table.rows[start:stop], rates[start:stop].tolist(),
                                        flags[start:stop].tolist(), tails, strict=True):
                buf.write(f"{line},{r[0]:.6f},{r[1]:.6f},{r[2]:.6f},{int(f[0])},{int(f[1])},{int(f[2])}{tail}\n")
            out.write(buf.getvalue())
            progress.update(stop)


def apply_imu_canlog(args: argparse.Namespace, corrector) -> int:
    """A CAN log, read as the daemon reads the bus: one row per raw frame, the three axes' signals.

    Writes time_s, raw_x, raw_y, raw_z, the inputs the sets (and the tracking) need, the three
    rates and flags (and the three tracked biases).
    """
    import numpy as np

    from canical.commands.apply import use_daemon_tracking
    from canical.commands.canlog_args import canlog_source, refuse_raw_for_a_triad
    from canical.files.atomic_file import atomic_writer
    from canical.sessions.canlog import TIME_INPUT

    imu = corrector.imu
    source = canlog_source(args, args.input)
    refuse_raw_for_a_triad(source, "apply")
    sensor = args.sensor or source.sensor
    if sensor and sensor != imu.sensor_id:
        raise CanicalError(f"{args.coefficients} is for sensor {imu.sensor_id}, "
                           f"{args.input} is from {sensor}")
    needed = list(corrector.required_inputs)
    if args.track_bias:
        use_daemon_tracking(args)
        wanted = ("time_s", args.standstill_column, args.temp_column)
        needed += [n for n in wanted if n and n in source.inputs]
    unmapped = [n for n in dict.fromkeys(needed) if n not in source.inputs]
    if unmapped:
        raise CanicalError(f"the IMU set needs input(s) {', '.join(unmapped)}: map them with "
                           "--input NAME=MESSAGE.Signal or --config")
    # Axes held from other messages: every axis's read needs them all, so the rows are the same.
    needed += [r for r in source.raw_signals.values() if r in source.inputs]
    sessions = [_axis_log(args, source, axis, list(dict.fromkeys(needed))) for axis in AXES]
    session = sessions[0]
    raw = np.column_stack([s.raw for s in sessions])
    inputs = dict(session.aux)
    if TIME_INPUT in corrector.required_inputs:
        inputs[TIME_INPUT] = session.time_s
    rates, flags = corrector.correct(raw, inputs)
    bias = None
    if args.track_bias:
        from canical.commands.track_bias import tracked_bias

        bias = tracked_bias(args, [c.fit for c in imu.axes], AXES, {**session.aux, "time_s": session.time_s},
                            rates, imu_source(imu))
    names = ["time_s", *RAW_NAMES, *session.aux, *RATE_COLUMNS, *FLAG_COLUMNS,
             *(BIAS_COLUMNS if bias is not None else ())]
    table = np.column_stack([session.time_s, raw, *session.aux.values(), rates, flags.astype(float),
                             *([bias] if bias is not None else [])])
    fmt = ["%.6f", *["%.9g"] * (3 + len(session.aux)), *["%.6f"] * 3, *["%d"] * 3,
           *(["%.6f"] * 3 if bias is not None else [])]
    with atomic_writer(args.output) as out:
        for key, value in session.meta.items():
            if key != "axis":
                out.write(f"# {key}: {value}\n")
        out.write(",".join(names) + "\n")
        buf = io.StringIO()
        np.savetxt(buf, table, delimiter=",", fmt=fmt)
        out.write(buf.getvalue())
    n_out = int(np.count_nonzero(flags.any(axis=1)))
    note = f", {n_out} with an axis outside its calibrated span (flagged)" if n_out else ""
    print(f"apply: {len(session)} {source.raw_message} frames corrected with IMU set "
          f"0x{corrector.set_id:08x}{note} -> {args.output}")
    return 0


RAW_NAMES = tuple(f"raw_{a}" for a in AXES)


def _axis_log(args: argparse.Namespace, source, axis: str, inputs: list[str]):
    """One axis's raw signal from the log, with the inputs: the same frames for every axis."""
    from canical.sessions.canlog import read_canlog

    return read_canlog(args.input, dbc=source.dbc, axis=axis, inputs={n: source.inputs[n] for n in inputs},
                       ref=None, raw_message=source.raw_message, raw_signal=source.raw_signals.get(axis),
                       sensor=source.sensor, j1939_source=source.j1939_source).session
