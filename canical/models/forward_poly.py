"""The forward model (paper eq. 5): ΔV as one polynomial of ω, inverted numerically.

It fits the sensor the way the physics reads (input rate → output), but at run
time the device knows ΔV and needs ω: a root of a polynomial per sample. This is
the cost that motivated the paper, kept here correct (safeguarded Newton) so it
can be measured against the closed-form segmented models.
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from canical.errors import CanicalError

NEWTON_TOL_DPS = 1e-9
NEWTON_MAX_ITER = 40


@dataclass(frozen=True)
class ForwardPoly:
    """ΔV = Σ a_k (ω/rate_scale)^k over the calibrated rate span."""

    coeffs: np.ndarray  # ascending powers of ω/rate_scale, ΔV units
    rate_scale: float
    rate_span: tuple[float, float]
    _c: list[float] = field(init=False, repr=False, compare=False)

    def __post_init__(self) -> None:
        object.__setattr__(self, "coeffs", np.asarray(self.coeffs, dtype=float).reshape(-1))
        object.__setattr__(self, "rate_span", (float(self.rate_span[0]), float(self.rate_span[1])))
        object.__setattr__(self, "_c", [float(c) for c in self.coeffs])

    @property
    def order(self) -> int:
        return int(self.coeffs.shape[0] - 1)

    @property
    def span(self) -> tuple[float, float]:
        """Calibrated ΔV span: the polynomial at the ends of the rate span."""
        a, b = self.forward(np.array(self.rate_span))
        return (float(min(a, b)), float(max(a, b)))

    def forward(self, rate: np.ndarray) -> np.ndarray:
        dv: np.ndarray = np.polynomial.polynomial.polyval(np.asarray(rate) / self.rate_scale, self.coeffs)
        return dv

    def _derivative(self, rate: np.ndarray) -> np.ndarray:
        d = np.polynomial.polynomial.polyder(self.coeffs)
        return np.polynomial.polynomial.polyval(np.asarray(rate) / self.rate_scale, d) / self.rate_scale

    def evaluate(self, dv: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """ω for each ΔV by vectorised safeguarded Newton; linear beyond the span."""
        dv = np.asarray(dv, dtype=float)
        lo, hi = self.span
        out = (dv < lo) | (dv > hi)
        target = np.clip(dv, lo, hi)
        w_lo, w_hi = self.rate_span
        # Start from the chord through the span ends, which is monotone like the sensor.
        dv_lo, dv_hi = self.forward(np.array([w_lo, w_hi]))
        w = w_lo + (target - dv_lo) * (w_hi - w_lo) / (dv_hi - dv_lo)
        for _ in range(NEWTON_MAX_ITER):
            step = (self.forward(w) - target) / self._derivative(w)
            w = np.clip(w - step, w_lo, w_hi)
            if np.max(np.abs(step), initial=0.0) < NEWTON_TOL_DPS:
                break
        if out.any():
            w = np.where(out, w + (dv - target) / self._derivative(w), w)
        return w, out

    def evaluate_one(self, dv: float) -> tuple[float, bool]:
        """Scalar Newton for one sample: the per-frame cost of this model."""
        c = self._c
        s = self.rate_scale
        lo, hi = self.span
        x = lo if dv < lo else hi if dv > hi else dv
        w_lo, w_hi = self.rate_span
        w = 0.5 * (w_lo + w_hi)
        for _ in range(NEWTON_MAX_ITER):
            u = w / s
            f = c[-1]
            df = 0.0
            for k in range(len(c) - 2, -1, -1):
                df = df * u + f
                f = f * u + c[k]
            step = (f - x) / (df / s)
            w = min(max(w - step, w_lo), w_hi)
            if abs(step) < NEWTON_TOL_DPS:
                break
        if x == dv:
            return w, False
        u = w / s
        df = 0.0
        for k in range(len(c) - 1, 0, -1):
            df = df * u + k * c[k]
        return w + (dv - x) / (df / s), True


def fit_forward_poly(rate: np.ndarray, dv: np.ndarray, weight: np.ndarray, order: int) -> ForwardPoly:
    """Weighted least squares ΔV(ω) of the given order; it must be monotone over the span."""
    if np.unique(rate).size <= order:
        raise CanicalError(f"forward-poly: order {order} needs more than {order} plateau rates")
    rate_scale = float(np.max(np.abs(rate))) or 1.0
    sw = np.sqrt(weight)
    x = np.vander(rate / rate_scale, order + 1, increasing=True)
    coeffs, *_ = np.linalg.lstsq(x * sw[:, None], dv * sw, rcond=None)
    model = ForwardPoly(coeffs, rate_scale, (float(np.min(rate)), float(np.max(rate))))
    grid = np.linspace(*model.rate_span, 512)
    slope = model._derivative(grid)
    if not (np.all(slope > 0) or np.all(slope < 0)):
        raise CanicalError(
            f"forward-poly: the order-{order} fit is not monotone over the rate span, so it has no inverse"
        )
    return model
