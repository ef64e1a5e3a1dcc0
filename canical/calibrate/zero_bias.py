"""Zero bias V0 from the zero-rate plateaus (the paper's equation (2): ΔV = V − V0)."""

from __future__ import annotations

import numpy as np

from canical.calibrate.plateaus import Plateaus, plateau_means
from canical.errors import CanicalError

ZERO_RATE_TOL_DPS = 1e-3


def zero_bias(raw: np.ndarray, plateaus: Plateaus, *, zero_tol: float = ZERO_RATE_TOL_DPS) -> float:
    """Sample-weighted mean raw output over all plateaus at zero table rate.

    Every zero-rate plateau of the session counts, so a session with several
    sweeps averages its zero bias over them.
    """
    zero = zero_rate(plateaus, zero_tol=zero_tol)
    if not zero.any():
        raise CanicalError("no zero-rate plateau in the session: the zero bias V0 cannot be measured")
    counts = (plateaus.stop - plateaus.start)[zero]
    means = plateau_means(raw, plateaus)[zero]
    return float(np.sum(means * counts) / np.sum(counts))


def zero_rate(plateaus: Plateaus, *, zero_tol: float = ZERO_RATE_TOL_DPS) -> np.ndarray:
    """Per plateau: whether the table stood still.

    A measured reference reads a zero plateau as its jitter averages out, not exactly 0,
    so the tolerance grows with how uncertain each plateau's rate is.
    """
    still: np.ndarray = np.abs(plateaus.rate_dps) <= np.maximum(zero_tol, 4.0 * plateaus.rate_uncertainty())
    return still
