"""Piecewise polynomials in ΔV: the run-time form of the segmented models.

Both segmented models end as the same thing on the device: for a raw value,
pick the segment by comparing ΔV = raw − V0 with the segment points, then
evaluate that segment's polynomial (equation (11) of the paper; the common model
(6) inverted per segment is the order-1 case). Polynomials are in the scaled
variable u = ΔV / scale so that coefficients stay well conditioned in float32
firmware as well as here.

Outside the calibrated span [lo, hi] nothing was measured, so a polynomial's
growth there is fiction. Values beyond the span are extrapolated *linearly* from
the value and slope at the span's edge and flagged as out of span.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np


@dataclass(frozen=True)
class PiecewisePoly:
    """Segments of ω(u), u = ΔV/scale; ``knots`` are interior segment points in ΔV."""

    knots: np.ndarray  # (S-1,) ascending, ΔV units
    coeffs: np.ndarray  # (S, m+1) ascending powers of u
    scale: float
    span: tuple[float, float]  # calibrated ΔV span
    # Plain-float copies for the scalar path, made once at load, not per frame.
    _knots_list: list[float] = field(init=False, repr=False, compare=False)
    _coeffs_list: list[list[float]] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "knots", np.asarray(self.knots, dtype=float).reshape(-1))
        object.__setattr__(self, "coeffs", np.atleast_2d(np.asarray(self.coeffs, dtype=float)))
        object.__setattr__(self, "span", (float(self.span[0]), float(self.span[1])))
        object.__setattr__(self, "_knots_list", [float(k) for k in self.knots])
        object.__setattr__(self, "_coeffs_list", [[float(c) for c in r] for r in self.coeffs])

    @property
    def knots_list(self) -> list[float]:
        """The knots as plain floats, made once at construction (the per-sample and compiled paths)."""
        return self._knots_list

    @property
    def coeffs_list(self) -> list[list[float]]:
        """The coefficient rows as plain floats, made once at construction."""
        return self._coeffs_list

    @property
    def n_segments(self) -> int:
        return int(self.coeffs.shape[0])

    @property
    def order(self) -> int:
        return int(self.coeffs.shape[1] - 1)

    def segment_of(self, dv: np.ndarray) -> np.ndarray:
        """Segment index for each ΔV (a value on a knot belongs to the upper segment)."""
        return np.searchsorted(self.knots, dv, side="right")

    def _horner(self, seg: np.ndarray, u: np.ndarray) -> np.ndarray:
        # One coefficient gathered per sample at a time, not each sample's whole row at once
        # (order + 1 times the samples' memory), from that power's own column (``take`` from a
        # short contiguous column is several times quicker than ``c[seg, k]``): the same
        # operations, the same values; the products and sums made in place.
        columns = [np.ascontiguousarray(col) for col in self.coeffs.T]
        out: np.ndarray = np.take(columns[-1], seg)
        for k in range(self.order - 1, -1, -1):
            out *= u
            out += np.take(columns[k], seg)
        return out

    def _slope(self, seg: np.ndarray, u: np.ndarray) -> np.ndarray:
        """dω/dΔV."""
        c = self.coeffs
        m = self.order
        if m == 0:
            return np.zeros_like(u)
        out: np.ndarray = m * c[seg, m]
        for k in range(m - 1, 0, -1):
            out = out * u + k * c[seg, k]
        return out / self.scale

    def slope(self, dv: np.ndarray) -> np.ndarray:
        """dω/dΔV at each ΔV (at the span edge beyond it, as the extrapolation uses)."""
        inside = np.clip(np.asarray(dv, dtype=float), *self.span)
        return self._slope(self.segment_of(inside), inside / self.scale)

    def evaluate(self, dv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """ω for each ΔV, and a boolean mask of values outside the calibrated span."""
        dv = np.asarray(dv, dtype=float)
        lo, hi = self.span
        out_of_span = (dv < lo) | (dv > hi)
        inside = np.clip(dv, lo, hi)
        seg = self.segment_of(inside)
        u = inside / self.scale
        rate = self._horner(seg, u)
        if out_of_span.any():
            if np.ndim(rate) == 0:
                rate = np.where(out_of_span, rate + self._slope(seg, u) * (dv - inside), rate)
            else:  # the few samples beyond the span, not the slope of every sample
                at = np.flatnonzero(out_of_span)
                rate[at] += self._slope(seg[at], u[at]) * (dv[at] - inside[at])
        return rate, out_of_span

    def evaluate_one(self, dv: float) -> tuple[float, bool]:
        """Scalar path for one sample: what a real-time loop pays per frame."""
        lo, hi = self.span
        x = lo if dv < lo else hi if dv > hi else dv
        seg = 0
        for knot in self._knots_list:
            if x >= knot:
                seg += 1
            else:
                break
        c = self._coeffs_list[seg]
        u = x / self.scale
        acc = c[-1]
        for k in range(len(c) - 2, -1, -1):
            acc = acc * u + c[k]
        if x == dv:
            return acc, False
        slope = 0.0
        for k in range(len(c) - 1, 0, -1):
            slope = slope * u + k * c[k]
        return acc + slope / self.scale * (dv - x), True

    def jumps(self) -> np.ndarray:
        """Discontinuity of ω at each knot (upper minus lower segment), deg/s."""
        if self.n_segments < 2:
            return np.zeros(0)
        u = self.knots / self.scale
        idx = np.arange(self.n_segments - 1)
        jump: np.ndarray = self._horner(idx + 1, u) - self._horner(idx, u)
        return jump
