"""Zero bias V0 from the zero-rate plateaus (the paper's equation (2): ΔV = V − V0)."""

from __future__ import annotations

import numpy as np

from canical.calibrate.plateaus import Plateaus, plateau_means
from canical.errors import CanicalError

ZERO_RATE_TOL_DPS = 1e-3
#: A sweep's V0: the windows within this many deg/s of zero...
ZERO_BAND_DPS = 2.0
MIN_ZERO_WINDOWS = 3  # ...at least this many on each side of zero


def zero_bias(raw: np.ndarray, plateaus: Plateaus, *, zero_tol: float = ZERO_RATE_TOL_DPS) -> float:
    """Sample-weighted mean raw output over all plateaus at zero table rate.

    Every zero-rate plateau of the session counts, so a session with several
    sweeps averages its zero bias over them. A continuous sweep has no zero plateau: its V0
    is where its windows cross zero (:func:`zero_crossing_bias`).
    """
    if plateaus.sweep_window_s > 0:
        return zero_crossing_bias(raw, plateaus)
    zero = zero_rate(plateaus, zero_tol=zero_tol)
    if not zero.any():
        raise CanicalError("no zero-rate plateau in the session: the zero bias V0 cannot be measured")
    counts = (plateaus.stop - plateaus.start)[zero]
    means = plateau_means(raw, plateaus)[zero]
    return float(np.sum(means * counts) / np.sum(counts))


def zero_crossing_bias(raw: np.ndarray, plateaus: Plateaus) -> float:
    """A sweep's V0: the output at zero rate of a parabola through the windows around zero.

    The windows within ``ZERO_BAND_DPS`` of zero, and at least the ``MIN_ZERO_WINDOWS`` nearest
    on each side: they bracket zero, so the line interpolates rather than extrapolates, and
    they are enough to average the noise. A parabola, not a line: the sensor bends there (its
    asymmetry's knee is even in the rate), which would lift a line's value at zero by the bend's
    mean over the band (0.007 deg/s for the simulated sensor's knee). What is left, a fraction of
    that, the fitted model's own constant term takes up (V0 only shifts ΔV).
    """
    rate = plateaus.rate_dps
    near = np.abs(rate) <= ZERO_BAND_DPS
    for side in (rate < 0, rate > 0):
        if not side.any():
            raise CanicalError("the sweep never crosses zero rate: the zero bias V0 cannot be measured; "
                               "sweep through zero")
        nearest = np.flatnonzero(side)[np.argsort(np.abs(rate[side]))[:MIN_ZERO_WINDOWS]]
        near[nearest] = True
    means = plateau_means(raw, plateaus)[near]
    return float(np.polyval(np.polyfit(rate[near], means, 2), 0.0))


def zero_rate(plateaus: Plateaus, *, zero_tol: float = ZERO_RATE_TOL_DPS) -> np.ndarray:
    """Per plateau: whether the table stood still (never, in a sweep's windows).

    A measured reference reads a zero plateau as its jitter averages out, not exactly 0,
    so the tolerance grows with how uncertain each plateau's rate is.
    """
    if plateaus.sweep_window_s > 0:
        return np.zeros(plateaus.count, dtype=bool)
    still: np.ndarray = np.abs(plateaus.rate_dps) <= np.maximum(zero_tol, 4.0 * plateaus.rate_uncertainty())
    return still
