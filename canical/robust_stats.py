"""Robust statistics the calibration shares, written once.

A Gaussian's standard deviation from the median absolute deviation (a few outliers or steps do
not move it), and a time series' typical step from the median of its positive steps (lost rows,
jitter and duplicated timestamps do not move it).
"""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

#: The MAD of a Gaussian times this is its standard deviation (1 / Φ⁻¹(3/4)).
MAD_TO_SIGMA = 1.4826


def mad_sigma(x: np.ndarray, center: float | None = None) -> float:
    """The standard deviation a Gaussian with the same median absolute deviation about ``center``
    (default: the median of ``x``) would have."""
    mid = np.median(x) if center is None else center
    return MAD_TO_SIGMA * float(np.median(np.abs(x - mid)))


def median_step(time_s: np.ndarray, default: float) -> float:
    """The rows' typical time step: the median of the positive steps; ``default`` when time never
    advances (a positive median is never 0, so 0.0 as ``default`` also says so)."""
    forward = positive_steps(time_s)
    # forward is this function's own copy: the median may reorder it rather than copy it again
    return float(np.median(forward, overwrite_input=True)) if forward.size else default


#: Steps taken at a time: a long record's steps are never all made at once beside their copy.
STEP_BLOCK = 1 << 20


def time_steps(time_s: np.ndarray) -> Iterator[tuple[int, np.ndarray]]:
    """``np.diff(time_s)`` a block at a time, with the index of each block's first step: the
    same values, in memory bounded by the block."""
    t = np.asarray(time_s, dtype=float)
    for a in range(0, t.size - 1, STEP_BLOCK):
        yield a, np.diff(t[a : a + STEP_BLOCK + 1])


def positive_steps(time_s: np.ndarray) -> np.ndarray:
    """The steps ``np.diff(time_s)`` that are positive, in order, gathered block by block (one
    array of them, not the steps and their copy)."""
    t = np.asarray(time_s, dtype=float)
    out = np.empty(max(t.size - 1, 0))
    n = 0
    for _, steps in time_steps(t):
        forward = steps[steps > 0]
        out[n : n + forward.size] = forward
        n += forward.size
    return out[:n]
