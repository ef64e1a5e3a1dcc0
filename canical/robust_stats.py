"""Robust statistics the calibration shares, written once.

A Gaussian's standard deviation from the median absolute deviation (a few outliers or steps do
not move it), and a time series' typical step from the median of its positive steps (lost rows,
jitter and duplicated timestamps do not move it).
"""

from __future__ import annotations

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
    dt = np.diff(np.asarray(time_s, dtype=float))
    forward = dt[dt > 0]
    # forward is this function's own copy: the median may reorder it rather than copy it again
    return float(np.median(forward, overwrite_input=True)) if forward.size else default
