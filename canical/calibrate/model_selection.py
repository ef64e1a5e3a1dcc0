"""Choose the number of segments and the polynomial order by held-out error.

More segments and higher orders always lower the training error; only error on
rates the fit did not see says whether they describe the sensor or its noise.
Orders above 3 are a second round, taken only when they are clearly better (see
:data:`HIGH_ORDERS`). Each candidate size is cross-validated (segment points re-chosen inside every
fold, since choosing them is part of the fit), and the *smallest* candidate whose
held-out rms is within one standard error of the best wins (the rms of n
held-out errors is uncertain by about 1/sqrt(2n) of itself): fewer coefficients are
cheaper on the device and safer between the calibrated rates. A candidate whose
ω(ΔV) is not monotone over the span, while the data is, is never chosen.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from canical.calibrate.cross_validation import HeldOutError, cross_validate_sizes
from canical.calibrate.fit_points import FitPoints
from canical.calibrate.model_fit import FittedModel, ModelSpec, fit_sizes
from canical.errors import CanicalError
from canical.models import RateModel

SEGMENT_CHOICES = (1, 2, 3, 4, 5, 6)
#: A continuous sweep's segment counts, its segment points evenly spaced
#: (:func:`~canical.calibrate.model_fit.even_knots`). Why more: segment points at residual
#: extrema ran out at 3-4 on a sweep's noisy windows, and its held-out error was then up to 3.5x
#: a step session's of the same sensor; with the same segment points as the step session's,
#: the sweep's windows fit as well as its plateaus, and a ripple or a knee wants more than six
#: evenly spaced ones. Up to 12: twice a step session's; with a cap of 8 or 16 instead,
#: ``tests/benchmarks/bench_sweep.py --seeds`` 70000-70059 gives the same verdicts (60/60 within the bar).
SWEEP_SEGMENT_CHOICES = tuple(range(1, 13))
ORDER_CHOICES = (1, 2, 3)
#: Orders tried in a second round, for a sensor that reached its rail inside the table's range or
#: bends toward one (:func:`end_compression`), or a continuous sweep (the caller decides:
#: :func:`canical.calibration.pipeline.fit_base`).
#: Why: an output stage that saturates bends the scale factor sharply in the last rates before
#: the rail, and orders up to 3 leave several times the noise there; a higher order removes most
#: of it. On a step session of a sensor orders up to 3 describe, a higher order's held-out rms is
#: as low only by chance, and choosing among more sizes by held-out rms then picks noise (offered
#: to every session, it failed a clean drifting sensor of ``tests/closed_loop/test_closed_loop.py``
#: ``test_clean_sensors_get_nothing_blamed_on_a_channel``), so the round is not offered there
#: at all, and where it is, its best must be clearly lower than the first round's best
#: (:func:`_clearly_better`).
HIGH_ORDERS = (4, 5)
#: Three standard errors: a sixth of the error gone on 200 held-out blocks, a third on 40. Where
#: a higher order is needed it removes far more (``tests/benchmarks/bench_rail.py`` prints it).
HIGH_ORDER_MARGIN = 3.0
#: ...and the typical fold must improve too: its held-out rms at most this share of the first
#: round's (a tenth lower).
TYPICAL_FOLD_RATIO = 0.9


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


#: A sign of an output bending toward its rail without reaching it: the sensitivity between the
#: last two rates at one end at least this share below the middle half's (see :func:`end_compression`).
END_COMPRESSION = 0.3


def end_compression(points: FitPoints) -> float:
    """How much less sensitive the sensor is between its last two rates at either end than over the
    middle half of its rates: 0 where it is as sensitive, 0.5 where half, the larger of the two ends.

    Why: an output stage bending toward a rail it never reaches compresses the top rates without
    clipping any plateau, so no plateau is left out to say the sensor has a rail, yet orders up to 3
    leave several times the noise there (:data:`HIGH_ORDERS`). A sensor those orders describe bends
    far less at its ends (the simulated paper sensor, ``GyroModel()``: 0.16; hard knees that never
    clip: 0.55 and more, on ``tests/benchmarks/bench_rail.py``'s development seeds). Plateau means
    are precise to a part in 10⁴ of the span, so neither noise nor a table's measured reference
    moves this figure.
    """
    merged = points.by_rate()
    rate, dv = merged.rate, merged.dv
    middle = np.abs(rate) <= 0.5 * np.max(np.abs(rate))
    if rate.size < 4 or np.count_nonzero(middle) < 2:
        return 0.0
    slope = float(np.polyfit(rate[middle], dv[middle], 1)[0])
    ends = np.array([(dv[1] - dv[0]) / (rate[1] - rate[0]), (dv[-1] - dv[-2]) / (rate[-1] - rate[-2])])
    return float(1.0 - np.min(ends / slope)) if slope else 0.0


def data_monotone(points: FitPoints) -> bool:
    merged = points.by_rate()
    d = np.diff(merged.dv)
    return bool(np.all(d > 0) or np.all(d < 0))


def evaluate_sizes(points: FitPoints, specs: list[ModelSpec]) -> list[Candidate | None]:
    """Cross-validate sizes differing only in their segments (:func:`fit_sizes`); ``None`` for each
    the data cannot support."""
    def models(p: FitPoints) -> list[RateModel | None]:
        return [None if f is None else f.model for f in fit_sizes(p, specs)]

    try:
        held = cross_validate_sizes(points, models)
    except CanicalError:  # too few rates to cross-validate any size
        return [None] * len(specs)
    full = fit_sizes(points, specs)
    return [_candidate(spec, h, f) for spec, h, f in zip(specs, held, full, strict=True)]


def _candidate(spec: ModelSpec, held: HeldOutError | None, full: FittedModel | None) -> Candidate | None:
    if held is None or full is None or full.spec.n_segments != spec.n_segments:
        return None  # a fold or the whole could not fit it, or too few suitable extrema for its segments
    n_coef = spec.n_segments * (spec.order + 1)
    return Candidate(spec, held, n_coef, is_monotone(full.model, full.model.span))


def select_model(
    points: FitPoints,
    base: ModelSpec,
    *,
    segments: tuple[int, ...] = SEGMENT_CHOICES,
    orders: tuple[int, ...] = ORDER_CHOICES,
    high_orders: tuple[int, ...] = (),
) -> tuple[ModelSpec, list[Candidate]]:
    """The chosen spec and every candidate tried (for the report).

    Orders in ``high_orders`` (none unless given) are a second round: they take part only when
    their best beats the first round's best clearly (see :data:`HIGH_ORDERS`).
    """
    candidates = _candidates(points, base, segments, orders)
    if not candidates:
        raise CanicalError("no model size fits this session: too few plateau rates")
    monotone = data_monotone(points)
    first = _choose(candidates, monotone)
    higher = _candidates(points, base, segments, tuple(o for o in high_orders if o not in orders))
    if not _clearly_better(_usable(higher, monotone), _usable(candidates, monotone)):
        return first.spec, candidates + higher
    return _choose(candidates + higher, monotone).spec, candidates + higher


def _candidates(points: FitPoints, base: ModelSpec, segments: tuple[int, ...],
                orders: tuple[int, ...]) -> list[Candidate]:
    tried = (evaluate_sizes(points, [replace(base, n_segments=n, order=o) for n in segments]) for o in orders)
    return [c for of_order in tried for c in of_order if c is not None]


def _usable(candidates: list[Candidate], monotone: bool) -> list[Candidate]:
    """The candidates that may be chosen: monotone ones where the data is (if any is)."""
    usable = [c for c in candidates if c.monotone] if monotone else candidates
    return usable or candidates


def _tolerance(best: Candidate) -> float:
    """The relative uncertainty of a held-out rms of n errors, about 1/sqrt(2n)."""
    return 1.0 / float(np.sqrt(2.0 * best.held_out.errors.size))


def _choose(candidates: list[Candidate], monotone: bool) -> Candidate:
    """The fewest coefficients among candidates within the tolerance of the best."""
    usable = _usable(candidates, monotone)
    best = min(usable, key=lambda c: c.held_out.rms_dps)
    good = [c for c in usable if c.held_out.rms_dps <= best.held_out.rms_dps * (1.0 + _tolerance(best))]
    return min(good, key=lambda c: (c.n_coefficients, c.held_out.rms_dps))


def _clearly_better(higher: list[Candidate], first: list[Candidate]) -> bool:
    """Whether the best of ``higher`` beats the best of ``first`` clearly: by more than
    :data:`HIGH_ORDER_MARGIN` of its standard errors (:func:`_tolerance`) overall, and in the
    typical fold (the median of the folds' ratios at most :data:`TYPICAL_FOLD_RATIO`).

    Why both: the standard error takes the held-out errors as independent; a drifting bias
    makes them correlated, and one fold whose drift a higher order happens to follow can then
    carry the overall figure alone.
    """
    if not higher:
        return False
    high = min(higher, key=lambda c: c.held_out.rms_dps)
    best = min(first, key=lambda c: c.held_out.rms_dps)
    overall = high.held_out.rms_dps < best.held_out.rms_dps * (1.0 - HIGH_ORDER_MARGIN * _tolerance(best))
    ratios = np.divide(high.held_out.fold_rms_dps, best.held_out.fold_rms_dps)
    return overall and float(np.median(ratios)) <= TYPICAL_FOLD_RATIO
