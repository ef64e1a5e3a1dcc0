"""The calibration pipeline: a session in, a coefficient set and a report out.

Pure: no files, no printing. Steps: find the settled plateaus, measure V0 on the
zero-rate ones, reduce to plateau means, choose the model size by held-out
error (or take the one asked for), fit, and gather the statistics a user needs
to trust the result.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np

from canical.calibrate.allan import NoiseAnalysis, NoiseSkipped
from canical.calibrate.cross_validation import cross_validate, prediction_errors
from canical.calibrate.fit_points import FitPoints, fit_points
from canical.calibrate.model_fit import FittedModel, ModelSpec, fit_model
from canical.calibrate.model_selection import (
    END_COMPRESSION,
    HIGH_ORDERS,
    ORDER_CHOICES,
    SEGMENT_CHOICES,
    SWEEP_SEGMENT_CHOICES,
    Candidate,
    end_compression,
    select_model,
)
from canical.calibrate.noise_records import name_a_rise, noise_analysis, sample_interval, zero_rate_records
from canical.calibrate.plateaus import Plateaus, detect_plateaus, explain_too_few
from canical.calibrate.rails import RailCheck, RailLimits, rail_plateaus
from canical.calibrate.segment_points import rate_noise
from canical.calibrate.sweep_windows import sweep_check, sweep_windows
from canical.calibrate.zero_bias import zero_bias, zero_rate
from canical.calibration.calibration_report import (
    CalibrationReport,
    ErrorStats,
    LeftOutPlateau,
    LoopSection,
    NoiseLevels,
    SampleCounts,
    SegmentPoint,
    SizeCandidate,
    Untestable,
    Written,
)
from canical.calibration.set_fit import set_fit
from canical.closed_loop.blocks import make_blocks
from canical.closed_loop.search import LoopResult, predict, run_loop
from canical.closed_loop.unexplained import account
from canical.errors import CanicalError
from canical.models.forward_poly import ForwardPoly
from canical.models.kinds import (
    FORWARD_POLY,
    MODEL_KINDS,
    SEGMENTED_INVERSE,
    SEGMENTED_LINEAR,
    ModelKind,
    model_kind,
)
from canical.models.piecewise import PiecewisePoly
from canical.models.segmented_linear import DEFAULT_BREAKPOINTS_DPS
from canical.sessions.session import Session
from canical.sets.coefficients import CoefficientSet
from canical.sets.set_model import SetModel, forward_model, piecewise_model
from canical.sets.terms import Term, merge_splines

FORWARD_ORDERS = (1, 2, 3, 4, 5, 6, 7)


@dataclass(frozen=True)
class CalibrateOptions:
    """What the user chose; ``None`` for segments/order means choose by held-out error."""

    model: str = SEGMENTED_INVERSE.name  # a name in MODEL_KINDS, as the command line gives it
    segments: int | None = None
    order: int | None = None
    smoothness: int | None = 0
    breakpoints_dps: tuple[float, ...] = DEFAULT_BREAKPOINTS_DPS
    rate_tol: float | None = None  # None: from the reference's estimated noise
    min_duration_s: float = 1.0
    settle_s: float | None = None  # None: 0.5 s or a tenth of the steady stretch
    latency_s: float | None = None  # the reference's latency behind the sensor; None: estimated
    extend: bool = True  # run the closed loop (segmented-inverse only)
    prefer: tuple[str, ...] = ()  # candidate names to pick when confounded
    direction_threshold_dps: float = 1.0

    @property
    def kind(self) -> ModelKind:
        """The registry's kind the option names (an unknown name is one line)."""
        kind = model_kind(self.model)
        if kind is None:
            raise CanicalError(f"model {self.model!r} unknown (known: {', '.join(MODEL_KINDS)})")
        return kind


@dataclass(frozen=True)
class BaseFit:
    """Everything the base (rate-only) calibration found, for the report and the closed loop."""

    plateaus: Plateaus
    v0: float
    points: FitPoints  # unsaturated plateaus only
    fitted: FittedModel
    saturated_rates: tuple[float, ...] = ()
    candidates: tuple[SizeCandidate, ...] = ()
    left_out: tuple[LeftOutPlateau, ...] = ()  # plateaus not fitted (at a rail), named for the user

    def kept(self) -> np.ndarray:
        """Per plateau: fitted (not left out at a rail)."""
        out = np.ones(self.plateaus.count, dtype=bool)
        out[[p.index for p in self.left_out]] = False
        return out


ProgressFn = Callable[[str], None]


def _quiet(_: str) -> None:
    pass


def fit_base(session: Session, options: CalibrateOptions, progress: ProgressFn = _quiet) -> BaseFit:
    """Plateaus, V0, points, and the fitted rate model (size chosen or given)."""
    session.reference()  # fail before any work when the table rate is missing
    progress("finding plateaus")
    plateaus = sweep_or_plateaus(session, find_plateaus(session, options), options, progress)
    if plateaus.count == 0:
        raise CanicalError(explain_too_few(plateaus, min_duration_s=options.min_duration_s,
                                           what="no constant-rate plateau found"))
    if not (plateaus.sweep_window_s or np.any(zero_rate(plateaus))):
        raise CanicalError(explain_too_few(
            plateaus, min_duration_s=options.min_duration_s,
            what=f"no zero-rate plateau among {plateaus.count} plateaus (V0 cannot be measured)"))
    v0 = zero_bias(session.raw, plateaus)
    means = session.means
    rails = rail_plateaus(session.raw, plateaus, rail_limits(session),
                          lowest=None if means is None else means.raw_low,
                          highest=None if means is None else means.raw_high)
    clipped = rails.left_out
    points = fit_points(session.raw, v0, plateaus, session.samples_per_row).take(~clipped)
    left_out = left_out_plateaus(session, plateaus, rails)
    if left_out:
        progress(f"left out {len(left_out)} plateaus at a rail of the sensor's output "
                 f"({', '.join(f'{p.rate_dps:g}' for p in left_out)} deg/s)")
    n_rates = int(points.rate_groups().max()) + 1
    if n_rates < 4:
        raise CanicalError(explain_too_few(
            plateaus, min_duration_s=options.min_duration_s,
            what=f"only {n_rates} distinct plateau rates (at least 4 are needed)"))
    progress(f"{plateaus.count} plateaus at {n_rates} rates; fitting {options.model}")
    bends = end_compression(points) >= END_COMPRESSION
    second_round = bool(clipped.any()) or bends or plateaus.sweep_window_s > 0
    spec, candidates = _choose_spec(points, options, second_round=second_round,
                                    sweep=plateaus.sweep_window_s > 0)
    fitted = fit_model(points, spec)
    sat_rates = tuple(float(r) for r in np.unique(plateaus.rate_dps[clipped]))
    return BaseFit(plateaus, v0, points, fitted, sat_rates, candidates, left_out)


def sweep_or_plateaus(session: Session, found: Plateaus, options: CalibrateOptions,
                      progress: ProgressFn = _quiet) -> Plateaus:
    """A continuous sweep with no zero plateau, as consecutive windows where its reference
    supports that (refused in one line where it does not); any other session's plateaus as found."""
    if not found.sweeping or np.any(zero_rate(found)):
        return found
    t, ref = session.time_s, session.reference()
    check = sweep_check(t, ref, session.raw, found)
    refusal = check.refusal()
    if refusal:
        raise CanicalError(explain_too_few(found, min_duration_s=options.min_duration_s,
                                           what="no constant-rate plateau found", why_not_sweep=refusal))
    windows = sweep_windows(t, ref, session.raw, found, check, options.latency_s)
    progress(f"a continuous sweep at {found.sweep_dps2:.3g} deg/s²: {windows.count} windows of "
             f"{check.window_s:.3g} s, sensor {-windows.latency_s * 1e3:.3g} ms behind the reference")
    return windows


def rail_limits(session: Session) -> RailLimits | None:
    """The session's rail as plateau checking takes it (None: no rail known)."""
    rail = session.rail
    return None if rail is None else RailLimits(rail.low, rail.high, rail.source, rail.resolution)


def left_out_plateaus(session: Session, plateaus: Plateaus, rails: RailCheck) -> tuple[LeftOutPlateau, ...]:
    """Each plateau left out at a rail: where it is and why, for the summary and the report."""
    t = session.time_s
    return tuple(
        LeftOutPlateau(index=int(i), rate_dps=float(plateaus.rate_dps[i]),
                       start_s=float(t[plateaus.start[i]]), stop_s=float(t[plateaus.stop[i] - 1]),
                       why=rails.why[i])
        for i in np.flatnonzero(rails.left_out))


def find_plateaus(session: Session, options: CalibrateOptions) -> Plateaus:
    """The session's plateaus with the user's thresholds (auto where not given)."""
    return detect_plateaus(
        session.time_s,
        session.reference(),
        rate_tol=options.rate_tol,
        min_duration_s=options.min_duration_s,
        settle_s=options.settle_s,
        settled=session.settled,
        latency_s=options.latency_s,
        raw=session.raw,
    )


def _choose_spec(points: FitPoints, o: CalibrateOptions, *, second_round: bool = False,
                 sweep: bool = False) -> tuple[ModelSpec, tuple[SizeCandidate, ...]]:
    """The model size: given, or chosen by held-out error; orders above 3 (``second_round``) only
    for a sensor that reached its rail inside the table's range or bends toward one, or a
    continuous sweep: its hundreds of windows resolve a bend 41 plateaus cannot (see
    :data:`HIGH_ORDERS`). A sweep's segment points are evenly spaced, and more of them are
    offered (see :data:`SWEEP_SEGMENT_CHOICES`)."""
    base = ModelSpec(o.kind, o.segments or 4, o.order or 2, o.smoothness, tuple(o.breakpoints_dps))
    if o.kind is SEGMENTED_LINEAR:
        return replace(base, order=1), ()
    if o.kind is FORWARD_POLY:
        if o.order is not None:
            return replace(base, order=o.order), ()
        spec, cands = select_model(points, base, segments=(1,), orders=FORWARD_ORDERS, high_orders=())
        return spec, tuple(_size_candidate(c) for c in cands)
    if o.segments is not None and o.order is not None:
        return base, ()
    if sweep:
        base = replace(base, even_points=True)
    choices = SWEEP_SEGMENT_CHOICES if sweep else SEGMENT_CHOICES
    segments = (o.segments,) if o.segments is not None else choices
    orders = (o.order,) if o.order is not None else ORDER_CHOICES
    high = HIGH_ORDERS if second_round and o.order is None else ()
    spec, cands = select_model(points, base, segments=segments, orders=orders, high_orders=high)
    return spec, tuple(_size_candidate(c) for c in cands)


def _size_candidate(c: Candidate) -> SizeCandidate:
    return SizeCandidate(segments=c.spec.n_segments, order=c.spec.order, coefficients=c.n_coefficients,
                         held_out_rms_dps=c.held_out.rms_dps, held_out_max_dps=c.held_out.max_dps,
                         monotone=c.monotone)


def set_model(fitted: FittedModel, v0: float) -> SetModel:
    """The coefficient set's form of a fitted model."""
    model = fitted.model
    if isinstance(model, ForwardPoly):
        return forward_model(model, v0)
    chosen = fitted.spec.kind.chooses_segment_points
    points_dps = (
        [e.rate_dps for e in fitted.extrema]
        if chosen
        else [b for b in fitted.spec.breakpoints_dps if model.span[0] < b]
    )
    smooth = fitted.spec.smoothness if chosen else None
    return piecewise_model(fitted.spec.kind, model, v0, smoothness=smooth, segment_points_dps=points_dps)


def error_stats(errors: np.ndarray) -> ErrorStats:
    return ErrorStats(rms_dps=float(np.sqrt(np.mean(errors**2))), max_dps=float(np.max(np.abs(errors))))


def base_report(session: Session, base: BaseFit) -> CalibrationReport:
    """The report of the base fit: samples, model, segment points, errors, noise; no Allan
    analysis (``allan`` is empty) and no loop yet."""
    spec = base.fitted.spec
    held = cross_validate(base.points, lambda p: fit_model(p, spec).model)
    train = prediction_errors(base.fitted.model, base.points)
    slope = float(np.polyfit(base.points.rate, base.points.dv, 1)[0])
    per_sample_noise = float(np.median(base.points.dv_sem * np.sqrt(base.points.weight))) / abs(slope)
    jumps = getattr(base.fitted.model, "jumps", None)
    k = session.samples_per_row  # a long session's rows are means of k samples: counts in samples
    return CalibrationReport(
        model=spec.kind.name,
        spec=spec.describe(),
        segments=spec.n_segments,
        order=spec.order,
        smoothness=spec.smoothness if spec.kind.chooses_segment_points else None,
        v0=base.v0,
        samples=SampleCounts(total=session.samples_read, used=base.plateaus.n_used * k,
                             transition=base.plateaus.n_transition * k,
                             settling=base.plateaus.n_settling * k),
        read_as_means=None if session.means is None else session.means.line(),
        plateaus=base.plateaus.count,
        plateau_finding=base.plateaus.describe(),
        saturated_rates_dps=base.saturated_rates,
        left_out_plateaus=base.left_out,
        rates=int(base.points.rate_groups().max()) + 1,
        segment_points=tuple(
            SegmentPoint(rate_dps=e.rate_dps, raw=e.dv + base.v0, prominence_dps=e.prominence_dps,
                         source=e.source)
            for e in base.fitted.extrema
        ),
        training=error_stats(train),
        held_out=error_stats(held.errors),
        noise=NoiseLevels(per_sample_dps=per_sample_noise,
                          plateau_mean_dps=float(np.median(rate_noise(base.points)))),
        candidates=base.candidates,
        allan=None,
        written=Written(spec=spec.describe(), effect_terms=0),
        max_jump_at_segment_points_dps=(
            float(np.max(np.abs(jumps()), initial=0.0)) if jumps is not None else None),
    )


def zero_rate_noise(session: Session, base: BaseFit) -> NoiseAnalysis | NoiseSkipped:
    """Allan analysis of the zero-rate plateaus, as rate through the fitted model.

    Only the plateaus' used samples count (no ramp, no settling); each plateau is its own
    record, so the longest τ is a third of the longest zero-rate plateau and terms that
    need longer (rate random walk, usually) are reported as not resolved.
    """
    zero = np.flatnonzero(zero_rate(base.plateaus))
    start, stop = base.plateaus.start[zero], base.plateaus.stop[zero]
    rate = np.zeros(len(session))
    for a, b in zip(start, stop, strict=True):
        rate[a:b] = base.fitted.model.evaluate(session.raw[a:b] - base.v0)[0]
    dt = sample_interval(session.time_s)
    records = zero_rate_records(session.time_s, rate, start, stop, dt)
    analysis = noise_analysis(records, dt, f"{zero.size} zero-rate plateaus")
    if isinstance(analysis, NoiseSkipped):
        return analysis
    if session.means is not None:
        # The records are means of k samples: the curve starts at τ = k samples (exact there
        # for non-overlapping clusters, fewer overlaps for the overlapping estimate).
        analysis = replace(analysis, samples_per_point=session.samples_per_row)
    temp = session.aux.get("temp_c")
    if temp is not None:
        inside = np.concatenate([temp[a:b] for a, b in zip(start, stop, strict=True)] or [np.zeros(0)])
        analysis = name_a_rise(analysis, "temperature", inside[np.isfinite(inside)], "°C")
    return analysis


@dataclass(frozen=True)
class CalibrationResult:
    coefficients: CoefficientSet
    report: CalibrationReport
    base: BaseFit
    loop: LoopResult | None = None


def extend_model(
    session: Session, base: BaseFit, options: CalibrateOptions, progress: ProgressFn = _quiet
) -> LoopResult:
    """Run the closed loop on the base fit: blocks, candidates, acceptance, joint refit."""
    model = base.fitted.model
    # The loop extends a segmented model's knots; calibrate() calls it for segmented-inverse fits only.
    if not isinstance(model, PiecewisePoly):
        raise CanicalError(f"the closed loop needs a segmented model, not {base.fitted.spec.kind}")
    slope = abs(float(np.polyfit(base.points.rate, base.points.dv, 1)[0]))
    keep = base.kept()
    blocks = make_blocks(
        session,
        base.plateaus,
        base.v0,
        keep=keep,
        direction_threshold_raw=options.direction_threshold_dps * slope,
    )
    duration = float(session.time_s[-1] - session.time_s[0])
    return run_loop(
        blocks,
        base.fitted.spec,
        model.knots,
        model.scale,
        model.span,
        duration,
        prefer=options.prefer,
        progress=progress,
    )


def fitted_residual(loop: LoopResult) -> np.ndarray:
    """The final model's residual at every block (deg/s), with the effects it found."""
    return loop.blocks.points.rate - predict(loop.fit, loop.blocks)


def loop_report(loop: LoopResult) -> LoopSection:
    """The closed loop's section: before/after on held-out plateaus, the rounds and steps."""
    return LoopSection(
        held_out_rms_before_dps=loop.rms_before,
        held_out_rms_after_dps=loop.rms_after,
        held_out_max_before_dps=float(np.nanmax(np.abs(loop.errors_before))),
        held_out_max_after_dps=float(np.nanmax(np.abs(loop.errors_after))),
        method=(f"leave-plateaus-out cross-validation on {loop.blocks.label}, "
                f"{int(np.isfinite(loop.errors_after).sum())} of {len(loop.blocks)} blocks held out; "
                "the extreme rates train every fold and are not in these figures"),
        extreme_rates_in_sample_rms_dps=loop.extreme_rms,
        block_s=loop.blocks.block_s,
        final_spec=loop.structure.spec.describe(),
        capacity_changes=tuple(loop.capacity_changes),
        untestable=tuple(Untestable(name, r2) for name, r2 in loop.untestable.items()),
        rounds=tuple(tuple(table) for table in loop.rounds),
        steps=tuple(loop.steps),
        bias_jumps_s=loop.bias_jumps_s,
    )


def with_loop(report: CalibrationReport, loop: LoopResult, n_terms: int) -> CalibrationReport:
    """The base report with what the closed loop found, and the loop's model as the one written."""
    return replace(
        report,
        effects=tuple(loop.effects),
        confounded=tuple(loop.confounded),
        closed_loop=loop_report(loop),
        unexplained=account(loop.errors_after, fitted_residual(loop), loop.blocks, loop.candidates),
        written=Written(spec=loop.structure.spec.describe(), effect_terms=n_terms),
    )


def calibrate(
    session: Session,
    options: CalibrateOptions,
    *,
    sensor_id: str,
    axis: str,
    raw_units: str = "counts",
    progress: ProgressFn = _quiet,
) -> CalibrationResult:
    """Fit the chosen model to a session (closing the loop unless told not to) and package the set."""
    base = fit_base(session, options, progress)
    progress("cross-validating the chosen model")
    report = base_report(session, base)
    progress("Allan deviation of the zero-rate plateaus")
    report = replace(report, allan=zero_rate_noise(session, base))
    model = set_model(base.fitted, base.v0)
    terms: tuple[Term, ...] = ()
    loop = None
    if options.extend and options.kind is SEGMENTED_INVERSE:
        progress("closing the loop: searching the residual for undeclared effects")
        loop = extend_model(session, base, options, progress)
        spec = loop.structure.spec
        points_dps = [
            float(np.interp(k, base.points.by_rate().dv, base.points.by_rate().rate))
            for k in loop.fit.poly.knots
        ]
        model = piecewise_model(
            spec.kind, loop.fit.poly, base.v0, smoothness=spec.smoothness, segment_points_dps=points_dps
        )
        terms = merge_splines(loop.fit.terms)  # a spline: one term
        report = with_loop(report, loop, len(terms))
    elif options.extend:
        report = replace(report, loop_skipped=f"the effect search needs the {SEGMENTED_INVERSE} model, "
                         f"not {options.model}")
    cset = CoefficientSet(
        sensor_id=sensor_id,
        axis=axis,
        v0=base.v0,
        model=model,
        terms=terms,
        fit=set_fit(report).to_dict(),
        created=dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
        raw_units=raw_units,
    )
    return CalibrationResult(cset, report, base, loop)
