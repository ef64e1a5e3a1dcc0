"""Sensors whose output compresses as it nears its rail, drawn at random, and their true error.

Why: an output stage that saturates bends the scale factor sharply in the last rates before the
rail, inside the table's range. The plateaus beyond the rail are clipped (and left out); the
ones just below it are compressed, and the model must follow that bend. These draws cover
knee sharpness, how far beyond the rail the compression's asymptote lies, where in the table's
range the rail falls, the sensitivity and the noise, so a verdict holds for the class and not
for one shape.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from canical.models import RateModel
from canical.sessions.session import Session
from canical.sim.gyro import GyroModel
from canical.sim.sessions import paper_rates, sweep_session


@dataclass(frozen=True)
class CompressingCase:
    """One drawn sensor, the session it gives on the table, and where its rail is."""

    gyro: GyroModel
    session: Session
    rail_dps: float
    limit_dps: float


def draw_compressing(seed: int, *, asymptote: tuple[float, float] = (1.02, 2.0)) -> CompressingCase:
    """A sensor clipping at 60-90 % of the table's range, compressing before it.

    ``asymptote``: the range of the compression's limit as a multiple of the rail (near 1: a hard
    knee just before the clip; 2: a gentle bend).
    """
    rng = np.random.default_rng(seed)
    limit = float(rng.choice([60.0, 90.0, 120.0]))
    sensitivity = float(rng.uniform(250.0, 450.0))
    rail_dps = float(rng.uniform(0.6, 0.9)) * limit
    rail = sensitivity * rail_dps
    gyro = GyroModel(sensitivity=sensitivity, full_scale_dps=limit, rail_counts=rail,
                     compression_counts=rail * float(rng.uniform(*asymptote)),
                     compression_sharpness=float(rng.uniform(2.5, 10.0)),
                     noise_dps=float(rng.uniform(0.03, 0.1)))
    session = sweep_session(gyro, paper_rates(limit / 20.0, limit), seed=seed)
    return CompressingCase(gyro, session, rail_dps, limit)


def true_error_dps(gyro: GyroModel, model: RateModel, v0: float, span_dps: tuple[float, float],
                   n: int = 400) -> float:
    """The rms of a model's rate against the truth over ``span_dps``, noise-free: its real error."""
    rate = np.linspace(span_dps[0], span_dps[1], n)
    dv = gyro.transfer(rate) + gyro.bias_counts - v0
    return float(np.sqrt(np.mean((model.evaluate(dv)[0] - rate) ** 2)))
