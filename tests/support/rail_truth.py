"""A fitted size's error against a compressing sensor's truth, and the references it is judged by.

Shared by the rail's test and its benchmark (``tests/benchmarks/bench_rail.py``): both judge the
chosen size against a polynomial fitted with hindsight, the one the issue names.
"""

from __future__ import annotations

from canical.calibrate.model_fit import ModelSpec, fit_model
from canical.calibration.pipeline import BaseFit
from canical.errors import CanicalError
from canical.models.kinds import FORWARD_POLY, SEGMENTED_INVERSE
from canical.sim.compression import CompressingCase, true_error_dps


def error_of(case: CompressingCase, base: BaseFit, spec: ModelSpec) -> float:
    """The error against the truth, over the fitted plateaus' span, of ``spec`` fitted on them."""
    rates = base.points.rate
    model = fit_model(base.points, spec).model
    return true_error_dps(case.gyro, model, base.v0, (float(rates.min()), float(rates.max())))


def hindsight(case: CompressingCase, base: BaseFit) -> float:
    """The best single polynomial, forward or inverse, order 1-9, picked by its true error."""
    errors = []
    for kind in (FORWARD_POLY, SEGMENTED_INVERSE):
        for order in range(1, 10):
            try:
                errors.append(error_of(case, base, ModelSpec(kind, 1, order)))
            except CanicalError:  # a forward polynomial that is not monotone has no inverse
                continue
    return min(errors)
