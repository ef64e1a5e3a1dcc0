"""The improved model (paper eqs. 10, 11): ω as a polynomial of ΔV in each segment.

Fitting ω(ΔV) directly means the run time needs no inverse. Beyond the paper,
the segments can be joined: with ``smoothness=0`` the fitted polynomials agree
at every segment point (C0), with ``smoothness=1`` their slopes agree too (C1).
That is a constrained least-squares problem; we solve it in the null space of
the constraint matrix, so every solution satisfies the joins exactly and the
remaining freedom is fitted by ordinary weighted least squares. ``smoothness=None``
fits each segment on its own, as the paper does.

Extra design columns (effect terms of the closed loop) can be fitted jointly.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import lru_cache

import numpy as np
from scipy.linalg import null_space

from canical.models.least_squares import NormalEquations
from canical.models.piecewise import PiecewisePoly


@dataclass(frozen=True)
class SegmentedFit:
    """A fitted piecewise polynomial and the coefficients of any extra columns."""

    poly: PiecewisePoly
    extra: np.ndarray


def design(dv: np.ndarray, knots: np.ndarray, order: int, scale: float) -> np.ndarray:
    """Block design matrix: the powers of u fill the columns of each point's segment."""
    n_seg, width = len(knots) + 1, order + 1
    seg = np.searchsorted(knots, dv, side="right")
    a = np.zeros((len(dv), n_seg, width))
    rows = np.arange(len(dv))
    # u**k as numpy.vander makes it (each power the last times u), written straight into its segment
    u = dv / scale
    power = np.ones_like(u)
    for k in range(width):
        a[rows, seg, k] = power
        power = power * u
    return a.reshape(len(dv), n_seg * width)


def join_constraints(knots: np.ndarray, order: int, scale: float, smoothness: int) -> np.ndarray:
    """Rows C such that C @ coeffs = 0 makes neighbouring segments agree at each knot."""
    n_seg = len(knots) + 1
    width = order + 1
    rows = []
    for j, knot in enumerate(knots):
        u = knot / scale
        for d in range(min(smoothness, order) + 1):
            # d-th derivative of u**k at u: k!/(k-d)! u**(k-d)
            vals = np.array(
                [np.prod(np.arange(k - d + 1, k + 1)) * u ** (k - d) if k >= d else 0.0 for k in range(width)]
            )
            row = np.zeros(n_seg * width)
            row[j * width : (j + 1) * width] = vals
            row[(j + 1) * width : (j + 2) * width] = -vals
            rows.append(row)
    return np.array(rows).reshape(len(rows), n_seg * width)


@lru_cache(maxsize=256)
def _join_basis(knots: tuple[float, ...], order: int, scale: float, smoothness: int) -> np.ndarray:
    """Null space of the joins, shared by every fit on the same segment points.

    The closed loop refits one set of segment points thousands of times (cross-validation
    folds, time-constant searches); the SVD behind this basis was an eighth of its time.
    Read-only, so no caller can change the cached copy.
    """
    basis: np.ndarray = null_space(join_constraints(np.asarray(knots), order, scale, smoothness))
    basis.setflags(write=False)
    return basis


@dataclass(frozen=True)
class JoinedDesign:
    """The weighted base columns of one fit (data, segment points, joins) and their normal
    equations, built once where many fits differ only in their extra columns: a time constant's
    search tries a score of lag features against the same blocks."""

    knots: np.ndarray
    order: int
    scale: float
    span: tuple[float, float]
    basis: np.ndarray
    sw: np.ndarray  # square roots of the weights
    equations: NormalEquations

    @classmethod
    def of(
        cls,
        dv: np.ndarray,
        rate: np.ndarray,
        weight: np.ndarray,
        knots: np.ndarray,
        order: int,
        *,
        scale: float,
        span: tuple[float, float],
        smoothness: int | None = 0,
    ) -> JoinedDesign:
        """The design of ω(ΔV) on these points, joined at the knots to ``smoothness``."""
        knots = np.sort(np.asarray(knots, dtype=float))
        a = design(dv, knots, order, scale)
        basis = np.eye(a.shape[1])
        if smoothness is not None and len(knots):
            basis = _join_basis(tuple(knots.tolist()), order, float(scale), smoothness)
        sw = np.sqrt(np.asarray(weight, dtype=float))
        equations = NormalEquations.of((a @ basis) * sw[:, None], rate * sw)
        return cls(knots, order, scale, span, basis, sw, equations)

    def fit(self, extra: np.ndarray | None = None) -> SegmentedFit:
        """The weighted least-squares fit, with ``extra`` columns (unweighted) fitted jointly."""
        equations = self.equations
        if extra is not None and extra.size:
            equations = equations.bordered(extra * self.sw[:, None])
        solution = equations.solve()
        n_base = self.basis.shape[1]
        coeffs = self.basis @ solution[:n_base]
        segments = coeffs.reshape(len(self.knots) + 1, self.order + 1)
        poly = PiecewisePoly(self.knots, segments, self.scale, self.span)
        return SegmentedFit(poly, solution[n_base:])


def fit_segmented_inverse(
    dv: np.ndarray,
    rate: np.ndarray,
    weight: np.ndarray,
    knots: np.ndarray,
    order: int,
    *,
    scale: float,
    span: tuple[float, float],
    smoothness: int | None = 0,
    extra: np.ndarray | None = None,
) -> SegmentedFit:
    """Weighted least-squares fit of ω(ΔV) per segment, optionally joined and with extra columns."""
    joined = JoinedDesign.of(dv, rate, weight, knots, order, scale=scale, span=span, smoothness=smoothness)
    return joined.fit(extra)
