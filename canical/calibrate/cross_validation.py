"""Held-out error by leaving out whole table rates.

Folds hold out every K-th distinct rate (all plateaus at that rate, so repeated
sweeps cannot leak), which puts the held-out rates *between* training rates —
the situation of a sensor in the field. The lowest and highest rates always
stay in training: judging a model outside its span would measure extrapolation,
which the run time flags instead of trusting.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
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
    held = cross_validate_sizes(points, lambda p: [fit(p)], k)[0]
    assert held is not None  # ``fit`` raises where it cannot fit
    return held


def cross_validate_sizes(
    points: FitPoints,
    fit: Callable[[FitPoints], Sequence[RateModel | None]],
    k: int = DEFAULT_FOLDS,
) -> list[HeldOutError | None]:
    """:func:`cross_validate` of several models fitted together (``fit`` returns one per size, ``None``
    where it could not fit that size): per size, its held-out errors, or ``None`` where any fold failed."""
    folds = rate_folds(points, k)
    errors: list[np.ndarray | None] = []
    fold_rms: list[list[float]] = []
    for f, held in enumerate(folds):
        models = fit(points.take(~held))
        if f == 0:
            errors = [np.full(len(points), np.nan) for _ in models]
            fold_rms = [[] for _ in models]
        test = points.take(held)
        for i, model in enumerate(models):
            e = errors[i]
            if model is None or e is None:
                errors[i] = None
                continue
            e[held] = prediction_errors(model, test)
            fold_rms[i].append(float(np.sqrt(np.mean(e[held] ** 2))))
    pairs = zip(errors, fold_rms, strict=True)
    return [None if e is None else _pooled(points, e, tuple(r)) for e, r in pairs]


def _pooled(points: FitPoints, errors: np.ndarray, fold_rms: tuple[float, ...]) -> HeldOutError:
    mask = ~np.isnan(errors)
    e = errors[mask]
    rms = float(np.sqrt(np.mean(e**2)))
    return HeldOutError(rms, float(np.max(np.abs(e))), e, points.rate[mask], fold_rms)
