"""``canical calibrate x.csv y.csv z.csv -o imu.yaml``: a triad's sessions to one IMU set.

Reached from :mod:`canical.commands.calibrate` when the sessions carry ``raw_x``, ``raw_y`` and
``raw_z`` (or more than one session is given). Writes the IMU set, and the report when asked
(``--report`` JSON; ``--report-dir``: report.json, report.md and coupling.png).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path
from typing import TYPE_CHECKING

from canical.errors import CanicalError
from canical.files.output_plan import output_plan
from canical.progress import Progress

if TYPE_CHECKING:
    from canical.calibration.imu_calibration_report import ImuReport

AXES = ("x", "y", "z")
#: Options of the single-axis flow a triad calibration does not take yet, and why one line says so.
SINGLE_AXIS_ONLY = (("rail", "--rail"), ("settled_column", "--settled-column"),
                    ("strict", "--strict"), ("axis", "--axis"))


def is_triad_input(args: argparse.Namespace) -> bool:
    """Several sessions, or one CSV with raw_x, raw_y, raw_z and no column named by --raw-column."""
    from canical.sessions.canlog_format import is_canlog
    from canical.sessions.csv_chunks import read_header
    from canical.sessions.triad_session import RAW_COLUMNS

    if len(args.session) > 1:
        return True
    path = args.session[0]
    if is_canlog(path):
        return False
    try:
        header = read_header(path)  # the head only: a session may be millions of rows
    except CanicalError:
        return False  # the single-axis reader says what is wrong, as it always did
    return all(c in header for c in RAW_COLUMNS) and args.raw_column not in header


def run_imu(args: argparse.Namespace) -> int:
    for attr, flag in SINGLE_AXIS_ONLY:
        if getattr(args, attr, None) not in (None, False):
            raise CanicalError(f"{flag} is not supported with three-axis sessions")
    check_references(args)
    with output_plan(args.output, args.report, dirs=[args.report_dir]):
        return calibrate_triad(args)


def calibrate_triad(args: argparse.Namespace) -> int:
    from canical.calibration.imu_pipeline import calibrate_imu
    from canical.commands.calibrate import calibrate_options, write_signed
    from canical.commands.trust_args import describe
    from canical.files.atomic_file import write_text_atomic
    from canical.sessions.canlog_format import is_canlog
    from canical.sessions.triad_session import read_triad_session
    from canical.sets import imu_set

    progress = Progress("calibrate", 1)
    sessions = []
    for k, path in enumerate(args.session):
        progress.step(f"reading {path}")
        if args.reference:
            sessions.append(read_triad_log_with_reference(args, path, args.reference[k]))
        else:
            sessions.append(read_triad_log_args(args, path) if is_canlog(path) else read_triad_session(path))
    sensors = {s.sensor_id for s in sessions if s.sensor_id}
    if args.sensor and sensors and sensors != {args.sensor}:
        raise CanicalError(f"--sensor {args.sensor} but the sessions were recorded from "
                           f"{', '.join(sorted(sensors))}")
    sensor = args.sensor or (sensors.pop() if len(sensors) == 1 else None)
    if not sensor:
        print("calibrate: no sensor id given (--sensor) or recorded; using 'unspecified'", file=sys.stderr)
        sensor = "unspecified"
    result = calibrate_imu(sessions, calibrate_options(args), sensor_id=sensor, progress=progress.step)
    report = result.report([str(p) for p in args.session], str(args.output))
    if args.sign_seed is None:
        imu_set.save(args.output, result.imu_set)
    else:
        signed = write_signed(args, imu_set.dumps(result.imu_set))
    if args.report:
        write_text_atomic(args.report, json.dumps(report.to_dict(), indent=2) + "\n")
    if args.report_dir:
        write_report_dir(Path(args.report_dir), report)
    print(summary(report, f"0x{imu_set.imu_set_crc(result.imu_set):08x}"))
    if args.sign_seed is not None:
        print(f"calibrate: {args.output} {describe(signed)}")
    return 0


def check_references(args: argparse.Namespace) -> None:
    """``--reference`` with three-axis sessions: one table file per CAN log, in the same order."""
    from canical.sessions.canlog_format import is_canlog

    if not args.reference:
        return
    if len(args.reference) != len(args.session):
        raise CanicalError(f"--reference: given {len(args.reference)} time(s) for {len(args.session)} "
                           "sessions: give each session's table file, in the sessions' order")
    csvs = [p for p in args.session if not is_canlog(p)]
    if csvs:
        raise CanicalError(f"--reference: {csvs[0]} is a CSV, which carries its table's rate (ref_dps): "
                           "--reference is for CAN logs recorded without the table's frame")


def read_triad_log_with_reference(args: argparse.Namespace, path: str, reference: str):
    """A triad session from a CAN log without the table's frame and the table's own file: the
    turning axis is the raw output with the widest spread (the other two are at rest), aligned
    to the file by the rate changes both show, its sign that of their correlation (an IMU
    mounted upside down turns against the table)."""
    from canical.commands.calibrate import reference_line
    from canical.sessions.canlog import default_inputs
    from canical.sessions.reference_clock import ReferenceClock, align_reference, join_reference
    from canical.sessions.triad_session import read_triad_log_unreferenced, triad_with_reference

    source = canlog_source_for_triad(args, path)
    inputs = dict(source.inputs) if (source.inputs or source.from_config) else default_inputs(source.dbc)
    for name in ("raw", "ref_dps"):
        inputs.pop(name, None)
    raws = read_triad_log_unreferenced(path, dbc=source.dbc, inputs=inputs, raw_message=source.raw_message,
                                       raw_signals=source.raw_signals, j1939_source=source.j1939_source)
    table = table_trace(args, reference)
    axis = turning_axis(raws.raw)
    fit = align_reference(raws.time_s, raws.raw[:, axis], table)
    joined = join_reference(raws.time_s, table, fit)
    session, r = triad_with_reference(raws, axis, joined.ref_dps, joined.inside)
    clock = ReferenceClock(reference, fit, int((~joined.inside).sum()))
    # Printed, not progress: the axis and its sign are inferred, and the user must see them.
    print(reference_line(clock))
    print(f"axis       {path}: the table turns about IMU axis {session.axis_label} (raw {AXES[axis]} "
          f"spreads most; correlation with the table's rate {r:+.3f})")
    return session


def turning_axis(raw) -> int:
    """The raw output that spreads most (1st to 99th percentile): the axis the table turns."""
    import numpy as np

    spread = np.nanpercentile(raw, 99, axis=0) - np.nanpercentile(raw, 1, axis=0)
    return int(np.argmax(spread))


def table_trace(args: argparse.Namespace, reference: str):
    """The table's own file (a CSV, or a CAN log read with the options' DBC and ref_dps signal)."""
    from canical.commands.canlog_args import canlog_source
    from canical.sessions.canlog import parse_signal_map
    from canical.sessions.canlog_format import is_canlog
    from canical.sessions.table_file import read_table_trace

    dbc = signal = j1939 = None
    if is_canlog(reference):
        source = canlog_source(args, reference)
        dbc, j1939 = source.dbc, source.j1939_source
        signal = parse_signal_map(args.inputs).get("ref_dps")
    return read_table_trace(reference, column=args.ref_column, dbc=dbc, signal=signal, j1939_source=j1939)


def canlog_source_for_triad(args: argparse.Namespace, path: str):
    from canical.commands.canlog_args import canlog_source, refuse_raw_for_a_triad

    source = canlog_source(args, path)
    refuse_raw_for_a_triad(source, "calibrate")
    return source


def read_triad_log_args(args: argparse.Namespace, path: str):
    """A triad session from a CAN log, with the DBC and mapping the options give (as the
    single-axis flow: --dbc/--config, --input ref_dps=MESSAGE.Signal, else TABLE_REF)."""
    from canical.commands.canlog_args import canlog_source, refuse_raw_for_a_triad
    from canical.sessions.canlog import default_inputs
    from canical.sessions.canlog_format import DEFAULT_REF
    from canical.sessions.triad_session import read_triad_log

    source = canlog_source(args, path)

    refuse_raw_for_a_triad(source, "calibrate")
    inputs = dict(source.inputs) if (source.inputs or source.from_config) else default_inputs(source.dbc)
    inputs.pop("raw", None)
    ref = inputs.pop("ref_dps", None) or DEFAULT_REF
    return read_triad_log(path, dbc=source.dbc, inputs=inputs, ref=ref, raw_message=source.raw_message,
                          raw_signals=source.raw_signals, j1939_source=source.j1939_source)


def write_report_dir(directory: Path, report: ImuReport) -> None:
    """report.json, report.md and coupling.png, side by side."""
    from canical.files.atomic_file import make_dirs, write_text_atomic
    from canical.report.imu_report import FIGURE, render, write_coupling_plot

    make_dirs(directory)
    write_coupling_plot(report, directory / FIGURE)
    write_text_atomic(directory / "report.json", json.dumps(report.to_dict(), indent=2) + "\n")
    write_text_atomic(directory / "report.md", render(report, [FIGURE]))


def summary(report: ImuReport, crc: str) -> str:
    """A few lines: each axis's model, the coupling in % and mrad, held-out errors before/after."""
    lines = [f"axis {a}     {ax.model}, held-out rms {ax.held_out_rms_dps:.4f} deg/s"
             for a, ax in zip(AXES, report.axes, strict=True)]
    lines.append(f"coupling   {report.coupling_plateaus} plateaus; off-diagonal terms "
                 "(% / mrad ± standard error %):")
    for t in report.off_diagonal:
        lines.append(f"           {t.row} from {t.column}  {t.percent:+.3f} %  "
                     f"{t.mrad:+.2f} mrad  ± {100 * t.standard_error:.4f} %")
    lines.append("held-out   plateau error rms per axis x/y/z, deg/s: per-axis only -> with coupling")
    for e in report.held_out:
        b = "/".join(f"{v:.4f}" for v in e.before_rms_dps)
        after = "/".join(f"{v:.4f}" for v in e.after_rms_dps)
        lines.append(f"           {e.session} ({e.axis}, {e.plateaus} plateaus): {b} -> {after}")
    lines.append(f"wrote      {report.coefficients}: IMU set 0x{crc[2:]} (three axes and their coupling)")
    return "\n".join(lines)
