"""Choose segment points from the extrema of a fit residual (paper section IV).

The paper fits ω(ΔV) with one quadratic over the whole span and places the
segment points at the extrema of its residual as a function of rate: there the
global curve departs most from the sensor and its curvature changes, so a
segment boundary there buys the most. On real, noisy data the residual has
wiggles from noise too. An extremum is *suitable* only when its prominence (how
far it rises above the lower of the neighbouring troughs) exceeds
``prominence_sigma`` standard errors of the plateau means (a prominence is a
difference of noisy points, and a sweep offers dozens of chances for a fluke); the most prominent
come first.

When more segments are asked for than the global residual offers, the search
continues on the residual of the segmented fit itself, adding one point at a
time at its most prominent extremum (our extension; reported as such).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from canical.calibrate.fit_points import FitPoints

PROMINENCE_SIGMA = 5.0
EVEN_SOURCE = "evenly spaced"  # an Extremum's source where segment points are spaced evenly, not found


@dataclass(frozen=True)
class Extremum:
    """A residual extremum: where (rate and ΔV) and how prominent, in deg/s."""

    rate_dps: float
    dv: float
    prominence_dps: float
    source: str  # "global-quadratic", "segmented-residual" or EVEN_SOURCE


def residual_extrema(
    rate: np.ndarray,
    dv: np.ndarray,
    residual: np.ndarray,
    noise: np.ndarray,
    *,
    prominence_sigma: float = PROMINENCE_SIGMA,
    source: str = "global-quadratic",
) -> list[Extremum]:
    """Interior extrema of ``residual`` over ``rate`` (sorted), most prominent first."""
    floor = prominence_sigma * float(np.median(noise)) if noise.size else 0.0
    found: list[Extremum] = []
    for sign in (1.0, -1.0):
        for i in local_maxima(sign * residual):
            p = prominence(sign * residual, i)
            if p >= max(floor, 1e-15):
                found.append(Extremum(float(rate[i]), float(dv[i]), p, source))
    return sorted(found, key=lambda e: -e.prominence_dps)


def local_maxima(x: np.ndarray) -> list[int]:
    """Interior maxima of ``x``, a flat top counted once at its middle (the rule of
    ``scipy.signal.find_peaks``).

    Why by hand: importing scipy.signal takes half a second of every calibration, and a residual
    has a few dozen points.
    """
    peaks, i, last = [], 1, x.size - 1
    while i < last:
        if x[i - 1] < x[i]:
            ahead = i + 1
            while ahead < last and x[ahead] == x[i]:
                ahead += 1
            if x[ahead] < x[i]:
                peaks.append((i + ahead - 1) // 2)
                i = ahead
        i += 1
    return peaks


def prominence(x: np.ndarray, peak: int) -> float:
    """How far the peak rises above the higher of the lowest points on either side before
    ``x`` rises above it (or ends): ``scipy.signal.peak_prominences``' definition."""
    top = x[peak]
    left = peak
    while left > 0 and x[left - 1] <= top:
        left -= 1
    right = peak
    while right < x.size - 1 and x[right + 1] <= top:
        right += 1
    return float(top - max(x[left:peak + 1].min(), x[peak:right + 1].min()))


def global_quadratic_residual(points: FitPoints) -> np.ndarray:
    """Residual ω − q(ΔV) of one weighted quadratic fit over the span (the paper's first step)."""
    scale = float(np.max(np.abs(points.dv))) or 1.0
    x = np.vander(points.dv / scale, 3, increasing=True)
    sw = np.sqrt(points.weight)
    coef, *_ = np.linalg.lstsq(x * sw[:, None], points.rate * sw, rcond=None)
    residual: np.ndarray = points.rate - x @ coef
    return residual


def rate_noise(points: FitPoints) -> np.ndarray:
    """Standard error of each point in deg/s: its ΔV mean's (converted by the mean slope) and
    its table rate's, independent, combined.

    Why the rate's too: a residual is ω − q(ΔV), so a measured reference's error on a plateau's
    rate is residual noise exactly as the sensor's is. Left out, the floor sits below what
    noise alone produces, and a fluke extremum of the reference's jitter becomes a segment
    point (seen: 0.05 deg/s jitter made cross-validation folds place points at -18 and -24
    deg/s, prominence 0.023-0.028 against a sensor-only floor of 0.021).
    """
    slope = np.polyfit(points.rate, points.dv, 1)[0] if len(points) > 1 else 1.0
    noise: np.ndarray = np.hypot(points.dv_sem / abs(slope), points.rate_uncertainty())
    return noise


def _segment_sizes_ok(dv_sorted: np.ndarray, knots: list[float], min_points: int) -> bool:
    counts = np.bincount(np.searchsorted(sorted(knots), dv_sorted, side="right"), minlength=len(knots) + 1)
    return bool(np.all(counts >= min_points))


def choose_knots(
    points: FitPoints,
    n_segments: int,
    *,
    min_points: int,
    refit_residual: Callable[[np.ndarray], np.ndarray] | None = None,
    prominence_sigma: float = PROMINENCE_SIGMA,
) -> tuple[np.ndarray, list[Extremum]]:
    """Up to ``n_segments − 1`` segment points in ΔV, and the extrema they came from.

    ``refit_residual(knots)`` returns the residual (per merged rate point) of the
    segmented model with those knots; it drives the search past the paper's
    global-quadratic extrema when more segments are wanted. A candidate point is
    skipped when it would leave a segment with fewer than ``min_points`` rates.
    """
    chosen = knot_sequence(points, n_segments, min_points=min_points, refit_residual=refit_residual,
                           prominence_sigma=prominence_sigma)
    return knots_of(chosen), sorted(chosen, key=lambda e: e.dv)


def knots_of(chosen: list[Extremum]) -> np.ndarray:
    """The segment points of chosen extrema, in ΔV order."""
    return np.sort(np.array([e.dv for e in chosen], dtype=float))


def knot_sequence(
    points: FitPoints,
    n_segments: int,
    *,
    min_points: int,
    refit_residual: Callable[[np.ndarray], np.ndarray] | None = None,
    prominence_sigma: float = PROMINENCE_SIGMA,
) -> list[Extremum]:
    """:func:`choose_knots`' extrema in the order they were chosen.

    Each point is chosen from those before it alone, so fewer segments' points are the first of
    this list: a model selection trying several segment counts of one order chooses them once.
    """
    merged = points.by_rate()
    noise = rate_noise(merged)
    dv_sorted = np.sort(merged.dv)
    chosen: list[Extremum] = []
    knots: list[float] = []

    def try_add(candidates: list[Extremum]) -> bool:
        for ext in candidates:
            if any(abs(ext.dv - k) < 1e-12 for k in knots):
                continue
            if _segment_sizes_ok(dv_sorted, [*knots, ext.dv], min_points):
                knots.append(ext.dv)
                chosen.append(ext)
                return True
        return False

    resid = global_quadratic_residual(merged)
    for ext in residual_extrema(merged.rate, merged.dv, resid, noise, prominence_sigma=prominence_sigma):
        if len(knots) >= n_segments - 1:
            break
        try_add([ext])
    while refit_residual is not None and len(knots) < n_segments - 1:
        resid = refit_residual(np.sort(np.array(knots)))
        cands = residual_extrema(
            merged.rate,
            merged.dv,
            resid,
            noise,
            prominence_sigma=prominence_sigma,
            source="segmented-residual",
        )
        if not try_add(cands):
            break
    return chosen
