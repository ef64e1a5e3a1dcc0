"""Fit one model specification to plateau points: the single entry point the pipeline,
cross-validation and the closed loop all use, so that each fits models the same way.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field, replace

import numpy as np

from canical.calibrate.fit_points import FitPoints
from canical.calibrate.segment_points import EVEN_SOURCE, Extremum, knot_sequence, knots_of
from canical.errors import CanicalError
from canical.models.forward_poly import ForwardPoly, fit_forward_poly
from canical.models.kinds import FORWARD_POLY, SEGMENTED_INVERSE, SEGMENTED_LINEAR, ModelKind
from canical.models.piecewise import PiecewisePoly
from canical.models.segmented_inverse import SegmentedFit, fit_segmented_inverse
from canical.models.segmented_linear import DEFAULT_BREAKPOINTS_DPS, fit_segmented_linear


@dataclass(frozen=True)
class ModelSpec:
    """What to fit: the model kind and its size."""

    kind: ModelKind = SEGMENTED_INVERSE
    n_segments: int = 4
    order: int = 2
    smoothness: int | None = 0  # None: independent segments (the paper); 0: C0; 1: C1
    breakpoints_dps: tuple[float, ...] = DEFAULT_BREAKPOINTS_DPS  # segmented-linear only
    #: Segment points evenly spaced in ΔV instead of at residual extrema (a continuous sweep's:
    #: see :func:`even_knots`).
    even_points: bool = False

    def describe(self) -> str:
        if self.kind is SEGMENTED_INVERSE:
            join = {None: "free", 0: "C0", 1: "C1"}[self.smoothness]
            even = " points=even" if self.even_points else ""
            return f"{self.kind} segments={self.n_segments} order={self.order} joins={join}{even}"
        if self.kind is SEGMENTED_LINEAR:
            return f"{self.kind} points={list(self.breakpoints_dps)} deg/s"
        return f"{self.kind} order={self.order}"


@dataclass(frozen=True)
class FittedModel:
    """A run-time model plus what the fit decided on the way."""

    # The two run-time forms a fit yields (each a RateModel); callers that need knots narrow to PiecewisePoly.
    model: ForwardPoly | PiecewisePoly
    spec: ModelSpec
    extrema: list[Extremum] = field(default_factory=list)


SPAN_MARGIN_SIGMA = 4.0


def dv_span(points: FitPoints) -> tuple[float, float]:
    """The calibrated ΔV span: the extreme plateau means widened by their sample noise.

    Single samples at the extreme table rates scatter around the plateau mean;
    without the margin half of them would be flagged out of span although the
    rate they measure was calibrated.
    """
    lo, hi = int(np.argmin(points.dv)), int(np.argmax(points.dv))
    sample_sd = points.dv_sem * np.sqrt(points.weight)
    return (
        float(points.dv[lo] - SPAN_MARGIN_SIGMA * sample_sd[lo]),
        float(points.dv[hi] + SPAN_MARGIN_SIGMA * sample_sd[hi]),
    )


def fit_model(points: FitPoints, spec: ModelSpec, *, sequence: list[Extremum] | None = None) -> FittedModel:
    """Fit ``spec`` to the points (segment points chosen on the way, for the segmented-inverse model).

    ``sequence``: segment points already chosen for at least as many segments (:func:`fit_sizes`).
    """
    if len(points) < 2:
        raise CanicalError("fewer than 2 plateaus: nothing to calibrate")
    span = dv_span(points)
    scale = max(abs(span[0]), abs(span[1])) or 1.0
    if spec.kind is FORWARD_POLY:
        model = fit_forward_poly(points.rate, points.dv, points.weight, spec.order)
        # Widen the rate bracket by the same sample-noise margin as the ΔV span.
        lo, hi = model.rate_span
        slope = abs(float(np.polyfit(points.rate, points.dv, 1)[0])) or 1.0
        margin_lo = (model.span[0] - span[0]) / slope
        margin_hi = (span[1] - model.span[1]) / slope
        model = replace(model, rate_span=(lo - max(margin_lo, 0.0), hi + max(margin_hi, 0.0)))
        return FittedModel(model, spec)
    if spec.kind is SEGMENTED_LINEAR:
        linear = fit_segmented_linear(
            points.dv, points.rate, points.weight, spec.breakpoints_dps, scale=scale, span=span
        )
        return FittedModel(linear, spec)
    if spec.kind is not SEGMENTED_INVERSE:
        raise CanicalError(f"unknown model kind {spec.kind.name!r}")
    inverse = _InverseFit.of(points, spec, span)
    if spec.even_points:
        knots, extrema = even_knots(inverse.merged, spec.n_segments, span)
    else:
        chosen = (inverse.sequence(spec.n_segments) if sequence is None else sequence)[: spec.n_segments - 1]
        knots, extrema = knots_of(chosen), sorted(chosen, key=lambda e: e.dv)
    fit = inverse.with_knots(knots)
    actual = replace(spec, n_segments=len(knots) + 1)
    return FittedModel(fit.poly, actual, extrema)


def fit_sizes(points: FitPoints, specs: Sequence[ModelSpec]) -> list[FittedModel | None]:
    """Sizes differing only in their number of segments, each fitted to the points (``None`` where
    the data cannot support it). Segment points at residual extrema are chosen once, for the
    most segments: fewer segments' are the first of them (:func:`knot_sequence`)."""
    sequence = _shared_sequence(points, specs)
    return [_fit_or_none(points, spec, sequence) for spec in specs]


def _shared_sequence(points: FitPoints, specs: Sequence[ModelSpec]) -> list[Extremum] | None:
    """The segment points of the most segments, in the order chosen; ``None`` where each size
    chooses its own (another kind, evenly spaced points, or a fit that fails: a size with fewer
    segments may still succeed)."""
    most = max(specs, key=lambda spec: spec.n_segments)
    if most.kind is not SEGMENTED_INVERSE or most.even_points or len(points) < 2:
        return None
    try:
        return _InverseFit.of(points, most, dv_span(points)).sequence(most.n_segments)
    except (CanicalError, np.linalg.LinAlgError):
        return None


def _fit_or_none(points: FitPoints, spec: ModelSpec, sequence: list[Extremum] | None) -> FittedModel | None:
    try:
        return fit_model(points, spec, sequence=sequence)
    except (CanicalError, np.linalg.LinAlgError):
        return None


@dataclass(frozen=True)
class _InverseFit:
    """A segmented-inverse fit of one order and joins to the points, for any segment points."""

    points: FitPoints
    merged: FitPoints
    spec: ModelSpec
    span: tuple[float, float]

    @classmethod
    def of(cls, points: FitPoints, spec: ModelSpec, span: tuple[float, float]) -> _InverseFit:
        merged = points.by_rate()
        n_rates = np.unique(merged.rate).size
        if n_rates < spec.order + 1:
            raise CanicalError(
                f"{spec.describe()}: needs at least {spec.order + 1} plateau rates, the session has {n_rates}"
            )
        return cls(points, merged, spec, span)

    def with_knots(self, knots: np.ndarray) -> SegmentedFit:
        p = self.points
        return fit_segmented_inverse(p.dv, p.rate, p.weight, knots, self.spec.order,
                                     scale=max(abs(self.span[0]), abs(self.span[1])) or 1.0,
                                     span=self.span, smoothness=self.spec.smoothness)

    def residual(self, knots: np.ndarray) -> np.ndarray:
        """Per merged rate, its rate minus the fit's with these segment points."""
        residual: np.ndarray = self.merged.rate - self.with_knots(knots).poly.evaluate(self.merged.dv)[0]
        return residual

    def sequence(self, n_segments: int) -> list[Extremum]:
        """Segment points at residual extrema for up to ``n_segments``, in the order chosen."""
        return knot_sequence(self.points, n_segments, min_points=self.spec.order + 1,
                             refit_residual=self.residual)


def even_knots(merged: FitPoints, n_segments: int,
               span: tuple[float, float]) -> tuple[np.ndarray, list[Extremum]]:
    """``n_segments − 1`` segment points evenly spaced over the ΔV span, each named by its rate.

    Why not at extrema: a sweep's windows are short, so each is noisy (several times a
    plateau's noise), and a residual extremum must stand that many standard errors above its
    neighbours to count: the sensor's bends go unseen and the segments run out. The windows cover
    every rate, so evenly spaced points always have data on both sides, and their number is
    chosen by held-out error like any size.
    """
    knots = np.linspace(span[0], span[1], n_segments + 1)[1:-1]
    counts = np.bincount(np.searchsorted(knots, merged.dv), minlength=n_segments)
    if np.any(counts < 2):
        raise CanicalError(f"{n_segments} evenly spaced segments: a segment with fewer than 2 rates")
    by_dv = np.argsort(merged.dv)
    rates = np.interp(knots, merged.dv[by_dv], merged.rate[by_dv])
    return knots, [Extremum(float(r), float(k), 0.0, EVEN_SOURCE) for r, k in zip(rates, knots, strict=True)]
