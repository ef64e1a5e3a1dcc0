"""Choose the number of segments and the polynomial order by held-out error.

More segments and higher orders always lower the training error; only error on
rates the fit did not see says whether they describe the sensor or its noise.
Each candidate size is cross-validated (segment points re-chosen inside every
fold, since choosing them is part of the fit), and the *smallest* candidate whose
held-out rms is within one standard error of the best wins (the rms of n
held-out errors is uncertain by about 1/sqrt(2n) of itself): fewer coefficients are
cheaper on the device and safer between the calibrated rates. A candidate whose
ω(ΔV) is not monotone over the span, while the data is, is never chosen.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from canical.calibrate.cross_validation import HeldOutError, cross_validate
from canical.calibrate.fit_points import FitPoints
from canical.calibrate.model_fit import ModelSpec, fit_model
from canical.errors import CanicalError
from canical.models import RateModel

SEGMENT_CHOICES = (1, 2, 3, 4, 5, 6)
ORDER_CHOICES = (1, 2, 3)


@dataclass(frozen=True)
class Candidate:
    """One cross-validated model size."""

    spec: ModelSpec
    held_out: HeldOutError
    n_coefficients: int
    monotone: bool


def is_monotone(model: RateModel, span: tuple[float, float], n: int = 2048) -> bool:
    """Whether ω(ΔV) keeps one direction over the calibrated span."""
    rate = model.evaluate(np.linspace(span[0], span[1], n))[0]
    d = np.diff(rate)
    return bool(np.all(d > 0) or np.all(d < 0))


def data_monotone(points: FitPoints) -> bool:
    merged = points.by_rate()
    d = np.diff(merged.dv)
    return bool(np.all(d > 0) or np.all(d < 0))


def evaluate_candidate(points: FitPoints, spec: ModelSpec) -> Candidate | None:
    """Cross-validate one size; ``None`` when the data cannot support it."""
    try:
        held = cross_validate(points, lambda p: fit_model(p, spec).model)
        full = fit_model(points, spec)
    except (CanicalError, np.linalg.LinAlgError):
        return None
    if full.spec.n_segments != spec.n_segments:
        return None  # not enough suitable extrema for this many segments
    n_coef = spec.n_segments * (spec.order + 1)
    return Candidate(spec, held, n_coef, is_monotone(full.model, full.model.span))


def select_model(
    points: FitPoints,
    base: ModelSpec,
    *,
    segments: tuple[int, ...] = SEGMENT_CHOICES,
    orders: tuple[int, ...] = ORDER_CHOICES,
) -> tuple[ModelSpec, list[Candidate]]:
    """The chosen spec and every candidate tried (for the report)."""
    candidates = []
    for order in orders:
        for n in segments:
            cand = evaluate_candidate(points, replace(base, n_segments=n, order=order))
            if cand is not None:
                candidates.append(cand)
    if not candidates:
        raise CanicalError("no model size fits this session: too few plateau rates")
    usable = [c for c in candidates if c.monotone] if data_monotone(points) else candidates
    usable = usable or candidates
    best = min(usable, key=lambda c: c.held_out.rms_dps)
    tolerance = 1.0 / np.sqrt(2.0 * best.held_out.errors.size)
    good = [c for c in usable if c.held_out.rms_dps <= best.held_out.rms_dps * (1.0 + tolerance)]
    chosen = min(good, key=lambda c: (c.n_coefficients, c.held_out.rms_dps))
    return chosen.spec, candidates
