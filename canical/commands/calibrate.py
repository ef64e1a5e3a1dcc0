"""``canical calibrate``: fit a session, write one coefficient set and a report."""

from __future__ import annotations

import argparse
import json
import sys
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from canical.calibration.calibration_report import CalibrationReport
from canical.commands import COMMANDS
from canical.commands.canlog_args import add_canlog_arguments
from canical.errors import CanicalError
from canical.files.key_file import read_secret
from canical.files.output_plan import output_plan
from canical.models import MODEL_KINDS
from canical.progress import Progress
from canical.sessions.canlog_format import CANLOG_FORMATS

if TYPE_CHECKING:
    from canical.calibrate.plateaus import PlateauFinding
    from canical.closed_loop.search import LoopResult
    from canical.sessions.reference_clock import ReferenceClock
    from canical.sessions.session import Session
    from canical.sets.signing import SignatureRecord

# The fitting and plotting modules (numpy, scipy, matplotlib) are imported where they are
# used, so that `--help` and argument errors answer at once.

JOINS = {"free": None, "C0": 0, "C1": 1}
REF_INPUT = "ref_dps"  # --input ref_dps=MESSAGE.Signal: the table's rate
EXIT_UNEXPLAINED = 3  # --strict: the calibration leaves an unexplained residual (2 is bad input)
STRICT_RATIO = 3.0  # --strict without a value: this many times the session's noise floor


def _positive_ratio(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError("--strict takes a number (a multiple of the noise floor)") from None
    if not value >= 1.0:
        raise argparse.ArgumentTypeError("--strict must be at least 1 (a multiple of the noise floor)")
    return value


def _rail(text: str):
    from canical.sessions.session import parse_rail

    try:
        return parse_rail(text, "--rail")
    except CanicalError as exc:
        raise argparse.ArgumentTypeError(str(exc).removeprefix("--rail: ")) from None


def _auto_or_int(name: str, low: int, high: int):
    def parse(text: str) -> int | None:
        if text == "auto":
            return None
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be 'auto' or a whole number") from None
        if not low <= value <= high:
            raise argparse.ArgumentTypeError(f"{name} must be from {low} to {high}")
        return value

    return parse


def _auto_or_seconds(name: str, unit: str):
    def parse(text: str) -> float | None:
        if text == "auto":
            return None
        try:
            value = float(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{name} must be 'auto' or a number of {unit}") from None
        if not value >= 0 or value == float("inf"):
            raise argparse.ArgumentTypeError(f"{name} must be a finite number of {unit}, 0 or more")
        return value

    return parse


def add_plateau_arguments(parser: argparse.ArgumentParser) -> None:
    """Thresholds of plateau finding; 'auto' takes them from the session (see the report)."""
    parser.add_argument("--min-plateau", type=_auto_or_seconds("--min-plateau", "seconds"), default=1.0,
                        metavar="S", help="shortest steady stretch that counts as a plateau, s [1]")
    parser.add_argument("--settle", type=_auto_or_seconds("--settle", "seconds"), default=None,
                        metavar="S", help="left out at the start of each plateau (table ringing, sensor "
                        "filter), s, or 'auto': how long the sensor's output takes to settle after each rate "
                        "change, as the session shows it (at least 0.1 s) [auto]")
    parser.add_argument("--rate-tol", type=_auto_or_seconds("--rate-tol", "deg/s"), default=None,
                        metavar="DPS", help="largest change of the reference's windowed median that is "
                        "still steady, deg/s, or 'auto': from the reference's estimated noise [auto]")
    parser.add_argument("--ref-latency", type=_auto_or_seconds("--ref-latency", "seconds"), default=None,
                        metavar="S", help="how late the reference is behind the sensor, s, cut from the "
                        "end of each plateau with its hold interval; 'auto': estimated from when sensor "
                        "and reference show each rate change [auto]")
    parser.add_argument("--settled-column", metavar="NAME",
                        help="CSV column with the table's settled flag (1 settled, 0 not); it narrows "
                        "plateaus, never widens them (CAN logs: TABLE_REF.TableSettled)")


def add_session_arguments(parser: argparse.ArgumentParser) -> None:
    """Options shared by commands that read a session."""
    parser.add_argument("--raw-column", default="raw", help="column with the raw sensor output")
    parser.add_argument("--ref-column", default="ref_dps", help="column with the table rate, deg/s")


def register(sub) -> None:
    p = sub.add_parser("calibrate", help=COMMANDS["calibrate"])
    p.add_argument(
        "session",
        nargs="+",
        help=f"session CSV (time_s, ref_dps, raw, auxiliary columns) or CAN log ({CANLOG_FORMATS}); "
        "for an IMU, one CSV per axis (raw_x, raw_y, raw_z and a '# axis:' line) and optionally a "
        "multi-axis one ('# axis: multi'), written as one IMU set",
    )
    p.add_argument("-o", "--output", required=True, help="coefficient set YAML to write")
    p.add_argument("--model", choices=MODEL_KINDS, default=MODEL_KINDS[0])
    p.add_argument(
        "--segments",
        type=_auto_or_int("--segments", 1, 12),
        default=None,
        help="number of segments, or 'auto' (held-out error) [auto]",
    )
    p.add_argument(
        "--order",
        type=_auto_or_int("--order", 1, 9),
        default=None,
        help="polynomial order, or 'auto' [auto]",
    )
    p.add_argument(
        "--joins",
        choices=tuple(JOINS),
        default="C0",
        help="continuity at segment points: free (the paper), C0, C1 [C0]",
    )
    p.add_argument(
        "--breakpoints",
        type=lambda s: tuple(float(x) for x in s.split(",")),
        default=(-10.0, 0.0, 10.0),
        help="segment rates of segmented-linear, deg/s",
    )
    p.add_argument(
        "--no-extend",
        action="store_true",
        help="fit the chosen model alone, without searching for undeclared effects",
    )
    p.add_argument("--report", help="JSON report to write")
    p.add_argument("--report-dir", help="folder for the full report: report.json, report.md and PNG plots")
    p.add_argument("--prefer", action="append", default=[], metavar="CANDIDATE",
                   help="when candidates are confounded, add this one (e.g. channel:temp_c, time:warm-up)")
    p.add_argument("--strict", nargs="?", type=_positive_ratio, const=STRICT_RATIO, default=None,
                   metavar="MULTIPLE",
                   help="exit with status 3 when the residual after the closed loop stays above MULTIPLE "
                   f"times the session's noise floor (unexplained) [{STRICT_RATIO:g}]; outputs are written. "
                   "Also exit with status 2, writing nothing, when candidates are confounded and none was "
                   "named with --prefer (the set would carry one adopted by rule)")
    p.add_argument("--reference", metavar="FILE", action="append",
                   help="the table controller's own recording of its rate on its own clock (with "
                   "three-axis CAN logs, one per log, in the same order; the turning axis is the raw "
                   "output that spreads most, its sign from the correlation with the table's rate): a CSV "
                   "(time_s and --ref-column) or a CAN log (--input ref_dps=MESSAGE.Signal, else "
                   "TABLE_REF.TableRate); aligned to the session by the rate changes both show (offset "
                   "and drift, reported). CAN logs name their gyro signal with --input raw=MESSAGE.Signal "
                   "and, without --reference, their table rate with --input ref_dps=MESSAGE.Signal")
    p.add_argument("--rail", type=_rail, metavar="LO,HI",
                   help="the raw signal's limits: plateaus at them are left out of the fit (default: the "
                   "DBC signal's range for a CAN log, the CSV's '# rail: LO,HI' line; none known: only "
                   "plateaus pinned to one extreme value)")
    p.add_argument("--sensor", help="sensor id (default: the session's '# sensor:' line)")
    p.add_argument("--axis", help="axis name (default: the session's '# axis:' line, else z)")
    p.add_argument("--sign-key", metavar="NAME.key",
                   help="sign the set with this private key (canical keygen), as one more than the "
                        "version of the signed set it replaces at -o, else version 1")
    add_session_arguments(p)
    add_plateau_arguments(p)
    add_canlog_arguments(p)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from canical.commands.calibrate_imu import is_triad_input, run_imu

    args.sign_seed = read_secret(args.sign_key) if args.sign_key else None  # a bad key: before any work
    if is_triad_input(args):
        return run_imu(args)
    args.session = args.session[0]
    if args.reference and len(args.reference) > 1:
        raise CanicalError(f"--reference: given {len(args.reference)} times for one session: give the "
                           "table's file once (one per session with three-axis sessions)")
    args.reference = args.reference[0] if args.reference else None
    with output_plan(args.output, args.report, dirs=[args.report_dir]):
        return calibrate_session(args)


def calibrate_session(args: argparse.Namespace) -> int:
    from canical.calibration.pipeline import calibrate
    from canical.commands.trust_args import describe
    from canical.files.atomic_file import write_text_atomic
    from canical.sessions.canlog_format import is_canlog
    from canical.sessions.csv_file import read_session
    from canical.sessions.session import RAW_UNITS
    from canical.sets import coefficient_file
    from canical.sets.coefficients import DEFAULT_RAW_UNITS

    progress = Progress("calibrate", 1)
    progress.step(f"reading {args.session}")
    if is_canlog(args.session):
        session = read_canlog_session(args, progress)
    else:
        session = read_session(args.session, raw_column=args.raw_column,
                               ref_column=None if args.reference else args.ref_column,
                               settled_column=args.settled_column, on_block=reading_progress(args.session))
        if session.means is not None:
            progress.step(session.means.line())
    clock = None
    if args.reference:
        session, clock = align_table_file(args, session, progress)
    if args.rail is not None:
        session = replace(session, rail=replace(args.rail, source="--rail"))
    sensor = args.sensor or session.sensor_id
    if args.sensor and session.sensor_id and args.sensor != session.sensor_id:
        raise CanicalError(f"--sensor {args.sensor} but {args.session} was recorded from {session.sensor_id}")
    if not sensor:
        print(
            "calibrate: no sensor id given (--sensor) or recorded; using 'unspecified'",
            file=sys.stderr,
        )
        sensor = "unspecified"
    options = calibrate_options(args)
    result = calibrate(
        session,
        options,
        sensor_id=sensor,
        axis=args.axis or session.axis or "z",
        raw_units=session.meta.get(RAW_UNITS, DEFAULT_RAW_UNITS),
        progress=progress.step,
    )
    report = result.report.with_paths(str(args.session), str(args.output)).with_reference_clock(clock)
    ruled = [c for c in report.confounded if c.adopted and not c.resolved_by_user]
    if args.strict is not None and ruled:
        c = ruled[0]
        print(f"calibrate: strict: the attribution is ambiguous ({' / '.join(c.candidates)} explain the "
              f"same residual); name one with --prefer, or {c.recommendation}", file=sys.stderr)
        return 2
    if args.sign_seed is None:
        coefficient_file.save(args.output, result.coefficients)
    else:
        signed = write_signed(args, coefficient_file.dumps(result.coefficients))
    if args.report:
        write_text_atomic(args.report, report_json(report))
    if args.report_dir:
        write_report_dir(Path(args.report_dir), report, result.loop)
    print(summary(report))
    if args.sign_seed is not None:
        print(f"calibrate: {args.output} {describe(signed)}")
    left = report.unexplained
    if args.strict is not None and (left is None or left.ratio > args.strict):
        why = (f"{left.ratio:.1f}× the noise floor, above --strict {args.strict:g}" if left
               else "no closed loop ran, so the residual was not checked")
        print(f"calibrate: strict: the residual stays unexplained ({why})", file=sys.stderr)
        return EXIT_UNEXPLAINED
    return 0


def write_signed(args: argparse.Namespace, text: str) -> SignatureRecord:
    """Write a set signed with ``--sign-key``: its version one more than that of the signed set it
    replaces (a vehicle refuses an older version), else 1; validated before it is written."""
    from canical.files.atomic_file import write_text_atomic
    from canical.sets.signed_file import next_version, sign_text

    signed, record = sign_text(text, str(args.output), args.sign_seed, next_version(args.output))
    write_text_atomic(args.output, signed)
    return record


def calibrate_options(args: argparse.Namespace):
    """The fitting options the command line chose (single-axis and three-axis flows alike)."""
    from canical.calibration.pipeline import CalibrateOptions

    return CalibrateOptions(
        model=args.model,
        segments=args.segments,
        order=args.order,
        smoothness=JOINS[args.joins],
        breakpoints_dps=args.breakpoints,
        extend=not args.no_extend,
        prefer=tuple(args.prefer),
        rate_tol=args.rate_tol,
        min_duration_s=args.min_plateau if args.min_plateau is not None else 1.0,
        settle_s=args.settle,
        latency_s=args.ref_latency,
    )


def report_json(report: CalibrationReport) -> str:
    """The report.json text."""
    return json.dumps(report.to_dict(), indent=2) + "\n"


def write_report_dir(directory: Path, report: CalibrationReport, loop: LoopResult | None) -> None:
    """report.json, report.md and the plots, side by side."""
    from canical.calibrate.allan import NoiseAnalysis
    from canical.files.atomic_file import make_dirs, write_text_atomic
    from canical.report.allan_plot import write_allan_plot
    from canical.report.markdown import render
    from canical.report.plots import write_plots

    make_dirs(directory)
    plots = [p.name for p in write_plots(loop, directory)] if loop is not None else []
    if isinstance(report.allan, NoiseAnalysis):
        plots.append(write_allan_plot(report.allan, directory / "allan.png",
                                      "Allan deviation, zero-rate plateaus").name)
    write_text_atomic(directory / "report.json", report_json(report))
    write_text_atomic(directory / "report.md", render(report, plots))


def reading_progress(path: str):
    """A session of hours takes seconds to read: a progress line in MB read."""
    import os

    try:
        size = os.path.getsize(path)
    except OSError:  # the reader says what is wrong with it
        size = 0
    reading = Progress("calibrate: reading", max(size >> 20, 1), unit="MB")
    return lambda done: reading.update(done >> 20)


def align_table_file(args: argparse.Namespace, session: Session, progress: Progress
                     ) -> tuple[Session, ReferenceClock]:
    """The session with the table's own file as its reference, aligned by the rate changes both show."""
    from canical.commands.canlog_args import canlog_source
    from canical.sessions.canlog import parse_signal_map
    from canical.sessions.canlog_format import is_canlog
    from canical.sessions.reference_clock import ReferenceClock, align_reference, join_reference
    from canical.sessions.table_file import read_table_trace

    dbc = signal = j1939 = None
    if is_canlog(args.reference):
        source = canlog_source(args, args.reference)
        dbc, j1939 = source.dbc, source.j1939_source
        signal = parse_signal_map(args.inputs).get(REF_INPUT)
    table = read_table_trace(args.reference, column=args.ref_column, dbc=dbc, signal=signal,
                             j1939_source=j1939)
    progress.step(f"aligning {args.reference} ({table.time_s.size} rows) to the session by its rate changes")
    fit = align_reference(session.time_s, session.raw, table)
    joined = join_reference(session.time_s, table, fit)
    clock = ReferenceClock(str(args.reference), fit, int((~joined.inside).sum()))
    progress.step(reference_line(clock))
    return replace(session, ref_dps=joined.ref_dps, settled=None).take(joined.inside), clock


def reference_line(clock: ReferenceClock) -> str:
    """One line on how the table's file was put on the session's clock."""
    outside = f", {clock.samples_outside} samples outside it left out" if clock.samples_outside else ""
    fit = clock.fit
    return (f"reference  {clock.file} on its own clock: offset {fit.offset_s:.4f} s, drift "
            f"{fit.drift_ppm:.1f} ppm, {fit.events} rate changes matched "
            f"(rms {fit.residual_ms:.1f} ms){outside}")


def read_canlog_session(args: argparse.Namespace, progress: Progress) -> Session:
    """A turntable session recorded from the bus: raw frames of one axis, the table's rate held.

    ``--input raw=MESSAGE.Signal`` names the gyro signal, ``--input ref_dps=MESSAGE.Signal`` the
    table's rate (without ``--reference``); every other input is an auxiliary channel.
    """
    from canical.commands.canlog_args import canlog_source
    from canical.sessions.canlog import default_inputs, read_canlog
    from canical.sessions.canlog_format import DEFAULT_REF

    source = canlog_source(args, args.session)
    given = source.inputs or source.from_config or source.raw_named
    inputs = dict(source.inputs) if given else default_inputs(source.dbc)
    named_ref = inputs.pop(REF_INPUT, None)
    raw_message = source.raw_message
    ref = None if args.reference else (named_ref or DEFAULT_REF)
    axis = args.axis
    if axis is None and source.raw_named:
        axis = "z"
    configured = tuple(source.raw_signals) if source.from_config else ()
    if axis is None:  # the table says which axis it turns; a first pass finds out
        probe = "z" if not configured or "z" in configured else configured[-1]
        first = read_canlog(args.session, dbc=source.dbc, axis=probe, inputs=source.axis_inputs(probe, []),
                            ref=None, raw_message=source.raw_message,
                            raw_signal=source.raw_signals.get(probe),
                            j1939_source=source.j1939_source)
        axis = first.table_axis or probe
    if configured and axis not in configured:
        raise CanicalError(f"calibrate: axis {axis} is not in {args.config}'s axes (it has "
                           f"{', '.join(configured)}): name it under axes.{axis}.raw, or give --axis")
    log = read_canlog(
        args.session,
        dbc=source.dbc,
        axis=axis,
        inputs=inputs,
        ref=ref,
        raw_message=raw_message,
        raw_signal=source.raw_signals.get(axis),
        sensor=args.sensor or source.sensor,
        j1939_source=source.j1939_source,
    )
    if log.table_axis and log.table_axis != axis:
        print(f"calibrate: warning: the table reports turning axis {log.table_axis}, calibrating {axis}",
              file=sys.stderr)
    channels = ", ".join(log.session.aux) or "none"
    progress.step(f"{len(log.session)} {raw_message} frames of axis {axis} from {log.frames} "
                  f"frames ({log.skipped} before the reference, {log.dropped} dropped); channels: {channels}")
    return log.session


def _plateau_line(found: PlateauFinding) -> str:
    return (f"plateaus   reference noise {found.reference_noise_dps:.3g} deg/s, tolerance "
            f"{found.rate_tol_dps:.3g} deg/s, held {found.reference_update_s:.3g} s, "
            f"late {found.reference_latency_s:.3g} s, {found.rate_changes} rate changes"
            + (f"; a continuous sweep, its plateaus {found.sweep_window_s:.3g} s windows"
               if found.sweep_window_s else ""))


def summary(report: CalibrationReport) -> str:
    """A few lines a calibration engineer reads first."""
    from canical.calibrate.allan import NoiseAnalysis  # numpy: --help does not import it

    s = report.samples
    lines = [
        f"rate model {report.spec} (size chosen on held-out plateau means)",
        f"samples    {s.used} of {s.total} used "
        f"({s.transition} at changing rate, {s.settling} settling), {report.plateaus} plateaus",
        *([f"input      {report.read_as_means}"] if report.read_as_means else []),
        _plateau_line(report.plateau_finding),
        *(f"left out   {p.label()}" for p in report.left_out_plateaus),
        f"V0         {report.v0:.3f}",
    ]
    if report.reference_clock is not None:
        lines.insert(0, reference_line(report.reference_clock))
    if report.segment_points:
        pts = ", ".join(f"{p.rate_dps:g}" for p in report.segment_points)
        lines.append(f"segments   at {pts} deg/s")
    tr, ho = report.training, report.held_out
    lines.append(f"training   rms {tr.rms_dps:.4f}  max {tr.max_dps:.4f} deg/s (plateau means)")
    lines.append(f"held-out   rms {ho.rms_dps:.4f}  max {ho.max_dps:.4f} deg/s "
                 "(plateau means, whole table rates left out)")
    loop = report.closed_loop
    if loop is not None:
        found = ", ".join(e.label for e in report.effects) or "none"
        lines.append(f"effects    {found}")
        for c in report.confounded:
            adopted = f" (ambiguous: adopted {c.adopted})" if c.adopted else ""
            lines.append(f"confounded {' / '.join(c.candidates)}{adopted}: {c.recommendation}")
        lines.append(f"loop       held-out rms, deg/s ({loop.blocks_label}, whole plateaus left out), "
                     "step by step:")
        for step in loop.steps:
            terms = f", {step.terms} effect terms" if step.terms else ""
            lines.append(f"           {step.held_out_rms_dps:.4f}  {step.step} ({step.spec}{terms})")
    allan = report.allan
    if isinstance(allan, NoiseAnalysis):
        lo, hi = allan.tau_range_s
        terms = "; ".join(f"{t.name} {t.value:.3g} {t.unit}" if t.resolved else f"{t.name} not resolved"
                          for _, t in allan.terms.items())
        lines.append(f"noise      {terms} (zero-rate plateaus, tau {lo:.2g}-{hi:.2g} s)")
    if report.unexplained is not None:
        from canical.closed_loop.unexplained import one_line

        lines.append(one_line(report.unexplained))
    lines.append(f"wrote      {Path(report.coefficients or '')}: {report.written_model()}")
    return "\n".join(lines)
