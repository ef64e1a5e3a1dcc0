"""A proof, at load, that a set's outputs are finite: a bound on |ω| over the span and beyond.

Why: a set file is checked field by field (finite numbers, ascending knots, known term kinds),
but finite fields can still make infinite rates: a coefficient of 1e308 passes every field
check and the extrapolation beyond the span then writes ``inf``. So loading also bounds the
output, by the triangle inequality on the very polynomials the run time evaluates, over an
envelope of what a run can feed the set:

* the raw output anywhere in the calibrated span or up to :data:`RAW_REACH` counts beyond
  either end (more than any 32-bit ADC count can be), and
* every auxiliary input (a channel, time since power-on, the raw output's rate of change)
  within ±:data:`INPUT_REACH` of zero, so each effect term's feature x is bounded by its
  kind's :meth:`~canical.sets.term_kinds.TermKind.reach`.

A set whose bound exceeds :data:`RATE_LIMIT_DPS` (far beyond any gyroscope, far below
overflow, so squares and sums of outputs stay finite too) is refused with one line naming the
field. Outside the envelope (a raw value of 1e300 in a CSV file) nothing is promised.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from canical.models.forward_poly import ForwardPoly
from canical.models.piecewise import PiecewisePoly
from canical.sets.terms import Term

#: How far beyond the span's ends a raw value may lie (counts): more than any 32-bit count.
RAW_REACH = 2.0**33
#: Largest |input| (channel units, seconds, raw counts per second) the bound covers.
INPUT_REACH = 1e9
#: Largest |ω| (deg/s) a set may give anywhere in the envelope.
RATE_LIMIT_DPS = 1e150
#: The flattest a forward polynomial's slope may be, as a share of its mean slope over the span.
#: Why: where ΔV(ω) is flat its inverse's gain is unbounded and Newton divides by (nearly) zero (a
#: slope of 5e-324 at ω = 0 between grid points raised ZeroDivisionError per sample).
MIN_SLOPE_SHARE = 1e-6
#: Rate-span points at which a forward polynomial's slope must keep one sign (as its fit checks).
FORWARD_GRID = 512


@dataclass(frozen=True)
class Unbounded:
    """Why the outputs are not bounded: the field to blame and a one-line reason."""

    field: str
    reason: str

    def message(self) -> str:
        return f"{self.field}: {self.reason}"


def shift_bound(terms: tuple[Term, ...], dv_reach: float) -> tuple[float, Unbounded | None]:
    """Largest |Σ c·x (·ΔV)| the terms add to ΔV, and the first term that makes it unbounded."""
    total = 0.0
    with np.errstate(all="ignore"):
        for i, term in enumerate(terms):
            share = abs(term.coefficient) * term.spec.reach(term, INPUT_REACH)
            if term.form == "scale":
                share *= dv_reach
            total += share
            if not total <= RATE_LIMIT_DPS:  # counts, but the same headroom suits them
                return total, Unbounded(f"terms[{i}].coefficient", f"{term.coefficient!r} makes the "
                                        f"correction unbounded (beyond {RATE_LIMIT_DPS:g} counts for "
                                        f"inputs within ±{INPUT_REACH:g})")
    return total, None


def _poly_bound(coeffs: np.ndarray, u: float) -> tuple[float, float]:
    """Bounds on |Σ c_k u^k| and |Σ k c_k u^(k-1)| for |u| ≤ ``u`` (ascending coefficients)."""
    a = np.abs(np.asarray(coeffs, dtype=float))
    powers = u ** np.arange(a.size, dtype=float)
    value = float(np.sum(a * powers))
    slope = float(np.sum(a[1:] * np.arange(1, a.size) * powers[:-1])) if a.size > 1 else 0.0
    return value, slope


def piecewise_bound(model: PiecewisePoly, reach: float) -> float:
    """Largest |ω| for ΔV within the span or ``reach`` beyond it (extrapolated by the edge slope)."""
    lo, hi = model.span
    edges = [lo, *model.knots_list, hi]
    with np.errstate(all="ignore"):
        rows = [_poly_bound(row, max(abs(a), abs(b)) / model.scale)
                for row, (a, b) in zip(model.coeffs, pairwise(edges), strict=True)]
        inside = max(v for v, _ in rows)
        ends = [rows[0], rows[-1]]
        beyond = max(v + s / model.scale * reach for v, s in ends)
    bound = max(inside, beyond)
    return bound if math.isfinite(bound) else math.inf


def forward_bound(model: ForwardPoly, reach: float) -> float:
    """Largest |ω| for ΔV within the span or ``reach`` beyond it; inf where Newton's arithmetic
    could overflow (ΔV(ω) beyond the limit) or the slope changes sign (no inverse: Newton may
    meet a zero slope)."""
    with np.errstate(all="ignore"):
        lo, hi = model.span
        grid = np.linspace(*model.rate_span, FORWARD_GRID)
        slope = model._derivative(grid)
        u = max(abs(model.rate_span[0]), abs(model.rate_span[1])) / model.rate_scale
        if not (np.isfinite(slope).all() and lo < hi and _poly_bound(model.coeffs, u)[0] <= RATE_LIMIT_DPS):
            return math.inf
        if not ((slope > 0).all() or (slope < 0).all()):
            return math.inf
        mean_slope = abs(hi - lo) / (model.rate_span[1] - model.rate_span[0])
        if not _flattest_slope(model) >= MIN_SLOPE_SHARE * mean_slope:
            return math.inf
        edge = float(min(abs(slope[0]), abs(slope[-1])))
        bound = max(abs(model.rate_span[0]), abs(model.rate_span[1])) + reach / edge
    return bound if math.isfinite(bound) else math.inf


def output_bound(model: PiecewisePoly | ForwardPoly, terms: tuple[Term, ...],
                 raw_span: tuple[float, float]) -> tuple[float, Unbounded | None]:
    """The bound on |ω| over the envelope (inf when there is none), and why it is unbounded.

    ``raw_span`` is the set's span in ΔV (``span_raw`` − V0): raw values up to :data:`RAW_REACH`
    beyond it, shifted by the terms, are what the model must take. For a segmented model it is
    the model's own span; a forward polynomial's span is where its ΔV(ω) takes the rate span.
    """
    with np.errstate(all="ignore"):
        lo, hi = model.span
    if not all(math.isfinite(v) for v in (lo, hi, *raw_span)):
        return math.inf, Unbounded("model", "the span relative to v0 overflows")
    dv_lo, dv_hi = raw_span[0] - RAW_REACH, raw_span[1] + RAW_REACH
    shift, unbounded = shift_bound(terms, max(abs(dv_lo), abs(dv_hi)))
    if unbounded is not None:
        return math.inf, unbounded
    reach = max(lo - (dv_lo - shift), (dv_hi + shift) - hi, 0.0)
    piecewise = isinstance(model, PiecewisePoly)
    bound = piecewise_bound(model, reach) if piecewise else forward_bound(model, reach)  # type: ignore[arg-type]
    if not bound <= RATE_LIMIT_DPS:
        return math.inf, Unbounded("model.coefficients", f"rates unbounded over the span and its "
                                   f"extrapolation (beyond ±{RATE_LIMIT_DPS:g} deg/s, or a forward "
                                   f"polynomial without an inverse)")
    return bound, None


def _flattest_slope(model: ForwardPoly) -> float:
    """The smallest |dΔV/dω| over the rate span: at its ends and wherever the slope turns (the
    second derivative's real roots), so a flat point between grid points is found too."""
    lo_u, hi_u = (w / model.rate_scale for w in model.rate_span)
    bend = np.polynomial.polynomial.polyder(model.coeffs, 2)
    roots = np.polynomial.polynomial.polyroots(bend) if bend.size > 1 and np.any(bend[1:]) else np.array([])
    turns = [r.real for r in np.atleast_1d(roots) if abs(r.imag) < 1e-12 and lo_u <= r.real <= hi_u]
    points = np.array([lo_u, hi_u, *turns]) * model.rate_scale
    return float(np.min(np.abs(model._derivative(points))))


def check_finite_outputs(model: PiecewisePoly | ForwardPoly, terms: tuple[Term, ...],
                         raw_span: tuple[float, float]) -> Unbounded | None:
    """None when every output in the envelope is within ±:data:`RATE_LIMIT_DPS`; else why not."""
    return output_bound(model, terms, raw_span)[1]


def check_coupled_outputs(matrix: np.ndarray, bounds: tuple[float, float, float]) -> Unbounded | None:
    """None when ``matrix @ rates`` stays within ±:data:`RATE_LIMIT_DPS` for any per-axis rates
    within their proven ``bounds``; else why not.

    Why: an IMU set's outputs are the coupling's rows applied to three per-axis outputs, each
    proven bounded alone; row i is at most Σ_j |M_ij|·bound_j (the triangle inequality again),
    so the proof carries through the product the run time computes."""
    with np.errstate(all="ignore"):
        rows = np.abs(np.asarray(matrix, dtype=float)) @ np.asarray(bounds, dtype=float)
    for i, row in enumerate(rows):
        if not row <= RATE_LIMIT_DPS:
            return Unbounded(f"coupling.matrix row {i + 1}", f"coupled rates unbounded (beyond "
                             f"±{RATE_LIMIT_DPS:g} deg/s over the axes' spans and extrapolation)")
    return None
