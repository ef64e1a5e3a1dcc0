"""The common model (paper eq. 6): ΔV linear in ω on segments split at chosen rates.

Each segment is fitted as ΔV = k0 + k·ω on the plateaus whose rate lies in it
(a plateau on a segment point belongs to both neighbours), and inverted on the
spot to ω = (ΔV − k0)/k, so that at run time it is the order-1 case of the same
piecewise polynomial in ΔV as the improved model. The segment point in ΔV is
where the two neighbouring lines are, on average, at the chosen rate.
"""

from __future__ import annotations

import itertools

import numpy as np

from canical.errors import CanicalError
from canical.models.piecewise import PiecewisePoly

DEFAULT_BREAKPOINTS_DPS = (-10.0, 0.0, 10.0)


def fit_segmented_linear(
    dv: np.ndarray,
    rate: np.ndarray,
    weight: np.ndarray,
    breakpoints_dps: tuple[float, ...] = DEFAULT_BREAKPOINTS_DPS,
    *,
    scale: float,
    span: tuple[float, float],
) -> PiecewisePoly:
    """Fit the common model and return it inverted, as ω(ΔV) per segment."""
    lo, hi = float(np.min(rate)), float(np.max(rate))
    inner = [b for b in sorted(breakpoints_dps) if lo < b < hi]
    edges = [-np.inf, *inner, np.inf]
    lines = []
    for a, b in itertools.pairwise(edges):
        sel = (rate >= a) & (rate <= b)
        if np.unique(rate[sel]).size < 2:
            raise CanicalError(f"segmented-linear: fewer than 2 plateau rates between {a:g} and {b:g} deg/s")
        sw = np.sqrt(weight[sel])
        x = np.column_stack([np.ones(sel.sum()), rate[sel]])
        (k0, k), *_ = np.linalg.lstsq(x * sw[:, None], dv[sel] * sw, rcond=None)
        lines.append((k0, k))
    knots = np.array(
        [
            0.5 * (lines[j][0] + lines[j][1] * w + lines[j + 1][0] + lines[j + 1][1] * w)
            for j, w in enumerate(inner)
        ]
    )
    coeffs = np.array([[-k0 / k, scale / k] for k0, k in lines])
    return PiecewisePoly(knots, coeffs, scale, span)
