"""Held-out error by leaving out whole table rates.

Folds hold out every K-th distinct rate (all plateaus at that rate, so repeated
sweeps cannot leak), which puts the held-out rates *between* training rates —
the situation of a sensor in the field. The lowest and highest rates always
stay in training: judging a model outside its span would measure extrapolation,
which the run time flags instead of trusting.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from canical.calibrate.fit_points import FitPoints
from canical.errors import CanicalError
from canical.models import RateModel

DEFAULT_FOLDS = 5


@dataclass(frozen=True)
class HeldOutError:
    """Errors of predicted minus true rate on held-out plateau means, deg/s."""

    rms_dps: float
    max_dps: float
    errors: np.ndarray  # per held-out point, in the order of ``rates``
    rates: np.ndarray
    #: Per fold: the rms of its held-out errors (one fold's big error shows here, not in a median).
    fold_rms_dps: tuple[float, ...] = ()


def rate_folds(points: FitPoints, k: int = DEFAULT_FOLDS) -> list[np.ndarray]:
    """Boolean held-out masks over ``points``, one per fold."""
    groups = points.rate_groups()
    n_groups = int(groups.max()) + 1
    if n_groups < 4:
        raise CanicalError(f"only {n_groups} distinct plateau rates: too few to cross-validate")
    k = max(2, min(k, n_groups - 2))
    inner = np.arange(1, n_groups - 1)
    return [np.isin(groups, inner[f::k]) for f in range(k)]


def prediction_errors(model: RateModel, points: FitPoints) -> np.ndarray:
    """Model output minus table rate at each point."""
    errors: np.ndarray = model.evaluate(points.dv)[0] - points.rate
    return errors


def cross_validate(
    points: FitPoints,
    fit: Callable[[FitPoints], RateModel],
    k: int = DEFAULT_FOLDS,
) -> HeldOutError:
    """Fit on each fold's training part, predict its held-out rates, pool the errors."""
    errors = np.full(len(points), np.nan)
    folds = []
    for held in rate_folds(points, k):
        model = fit(points.take(~held))
        errors[held] = prediction_errors(model, points.take(held))
        folds.append(float(np.sqrt(np.mean(errors[held] ** 2))))
    mask = ~np.isnan(errors)
    e = errors[mask]
    return HeldOutError(float(np.sqrt(np.mean(e**2))), float(np.max(np.abs(e))), e, points.rate[mask],
                        tuple(folds))
