"""Sub-plateau blocks: the points the closed loop fits, with the conditions of each.

Plateau means hide what changes within a plateau (a warm-up, a temperature
drifting while the table turns). The closed loop therefore cuts each plateau into
blocks of a few seconds and keeps, per block, the mean ΔV, the table rate, the
mean of every auxiliary channel, the mean time since power-on and the direction
state the run time would compute from the raw signal. Blocks of one plateau
share its ``plateau`` index, so cross-validation can leave whole plateaus out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from canical.fit_points import FitPoints
from canical.plateaus import Plateaus
from canical.session import Session
from canical.terms import direction_state, slope_state

BLOCK_S = 2.0
SLOPE_TAU_S = 0.5


@dataclass(frozen=True)
class Blocks:
    """Block means; ``points`` are what a rate model is fitted to."""

    points: FitPoints
    plateau: np.ndarray  # plateau index of each block
    time_s: np.ndarray
    aux: dict[str, np.ndarray]
    direction: np.ndarray  # mean run-time direction state in the block
    direction_threshold_raw: float
    slope: np.ndarray  # mean run-time rate of change of raw (raw units/s) in the block

    def __len__(self) -> int:
        return len(self.points)

    def take(self, index: np.ndarray) -> Blocks:
        return Blocks(
            self.points.take(index),
            self.plateau[index],
            self.time_s[index],
            {k: v[index] for k, v in self.aux.items()},
            self.direction[index],
            self.direction_threshold_raw,
            self.slope[index],
        )


def _block_bounds(plateaus: Plateaus, time_s: np.ndarray, block_s: float) -> tuple[np.ndarray, ...]:
    starts, stops, owner = [], [], []
    for p, (a, b) in enumerate(zip(plateaus.start, plateaus.stop, strict=True)):
        duration = time_s[b - 1] - time_s[a]
        n = max(1, int(duration // block_s))
        edges = np.linspace(a, b, n + 1).round().astype(int)
        starts.extend(edges[:-1])
        stops.extend(edges[1:])
        owner.extend([p] * n)
    return np.array(starts), np.array(stops), np.array(owner)


def make_blocks(
    session: Session,
    plateaus: Plateaus,
    v0: float,
    *,
    keep: np.ndarray | None = None,
    block_s: float = BLOCK_S,
    direction_threshold_raw: float,
) -> Blocks:
    """Cut the used plateaus (``keep`` masks plateaus, e.g. unsaturated ones) into blocks."""
    starts, stops, owner = _block_bounds(plateaus, session.time_s, block_s)
    if keep is not None:
        sel = keep[owner]
        starts, stops, owner = starts[sel], stops[sel], owner[sel]
    n = (stops - starts).astype(float)

    def means(values: np.ndarray) -> np.ndarray:
        csum = np.concatenate(([0.0], np.cumsum(values, dtype=float)))
        return (csum[stops] - csum[starts]) / n

    raw = session.raw
    mean_raw = means(raw)
    sd = np.sqrt(np.maximum(means(raw * raw) - mean_raw**2, 0.0) * n / np.maximum(n - 1, 1))
    rate = session.ref_dps
    points = FitPoints(means(rate), mean_raw - v0, n, sd / np.sqrt(n))
    direction = direction_state(raw, direction_threshold_raw)
    return Blocks(
        points=points,
        plateau=owner,
        time_s=means(session.time_s),
        aux={name: means(values) for name, values in session.aux.items()},
        direction=means(direction),
        direction_threshold_raw=direction_threshold_raw,
        slope=means(slope_state(raw, session.time_s, SLOPE_TAU_S)),
    )
