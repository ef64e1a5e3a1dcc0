"""Is the vehicle standing still? One window's statistics against the sensor's own noise.

Why these tests: at rest a gyro reads its bias plus white noise (and the engine's idle
vibration), so a still window's sample spread is what the set's angle random walk predicts,
and successive windows agree within their own uncertainty. Driving changes the rate from one
second to the next (steering, road), so it fails one test or the other. A steady turn passes
both, which is why the tracker also bounds the plausible bias; a cue (vehicle speed) settles
what the gyro cannot.

:class:`WindowSums` collects running sums per sample (O(1)); :func:`window_stats` turns them
into per-axis means, spreads and uncertainties once per window.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

from canical.tracking.config import TrackerConfig

STILL = "still"
CUE_MOVING = "cue"
BEYOND_BOUND = "bound"


@dataclass(frozen=True)
class WindowStats:
    """One closed window: per-axis mean, sample spread and uncertainty of the mean."""

    start_s: float
    end_s: float
    n: int
    mean_dps: tuple[float, ...]
    std_dps: tuple[float, ...]
    sigma_mean_dps: tuple[float, ...]
    temp_c: float
    cue_moving: bool
    quiet: bool  # every axis's spread is within what noise and idle vibration make


class WindowSums:
    """Running sums of one window (about its first sample, so no cancellation)."""

    __slots__ = ("cue_moving", "n", "ref", "s1", "s2", "start_s", "temp_sum")

    def __init__(self, axes: int) -> None:
        self.ref = [0.0] * axes
        self.s1 = [0.0] * axes
        self.s2 = [0.0] * axes
        self.n = 0
        self.start_s = 0.0
        self.temp_sum = 0.0
        self.cue_moving = False

    def restart(self, t_s: float, rates: Sequence[float]) -> None:
        self.ref = list(rates)
        self.s1 = [0.0] * len(self.ref)
        self.s2 = [0.0] * len(self.ref)
        self.n = 0
        self.start_s = t_s
        self.temp_sum = 0.0
        self.cue_moving = False


def window_stats(sums: WindowSums, end_s: float, config: TrackerConfig) -> WindowStats:
    """Close a window: means, spreads, and whether every axis's spread is quiet."""
    n = sums.n
    duration = end_s - sums.start_s
    rate_hz = (n - 1) / duration if duration > 0 and n > 1 else 1.0
    white = config.white_dps_rt_hz * math.sqrt(rate_hz)  # per-sample σ of white noise
    limit = config.k_std * white + config.vibration_dps
    means, stds, sigmas = [], [], []
    for ref, s1, s2 in zip(sums.ref, sums.s1, sums.s2, strict=True):
        var = max(s2 - s1 * s1 / n, 0.0) / (n - 1) if n > 1 else math.inf
        std = math.sqrt(var)
        means.append(ref + s1 / n)
        stds.append(std)
        sigmas.append(max(std, white) / math.sqrt(n))
    return WindowStats(
        start_s=sums.start_s,
        end_s=end_s,
        n=n,
        mean_dps=tuple(means),
        std_dps=tuple(stds),
        sigma_mean_dps=tuple(sigmas),
        temp_c=sums.temp_sum / n,
        cue_moving=sums.cue_moving,
        quiet=n >= 3 and all(s <= limit for s in stds),
    )


def steady(now: WindowStats, reference: Sequence[WindowStats], config: TrackerConfig) -> bool:
    """Quiet, and on every axis the same mean as the reference windows within their uncertainty.

    The reference is the run's last few windows (the quiet window before it when a run starts):
    a stop's bias does not move in seconds, slow turning in traffic does.
    """
    if not reference or not now.quiet or not all(w.quiet for w in reference):
        return False
    for a, (mean, sigma) in enumerate(zip(now.mean_dps, now.sigma_mean_dps, strict=True)):
        ref_mean, ref_sigma = pooled(reference, a)
        if abs(mean - ref_mean) > config.k_steady * math.hypot(sigma, ref_sigma):
            return False
    return True


def pooled(windows: Sequence[WindowStats], axis: int) -> tuple[float, float]:
    """Inverse-variance mean of one axis over windows, and its σ."""
    weights = [1.0 / (w.sigma_mean_dps[axis] ** 2) for w in windows]
    total = sum(weights)
    return sum(wt * w.mean_dps[axis] for wt, w in zip(weights, windows, strict=True)) / total, \
        math.sqrt(1.0 / total)


def verdict(window: WindowStats, config: TrackerConfig) -> str:
    """A steady window is learned from unless the cue says moving or a mean is past the bound."""
    if window.cue_moving:
        return CUE_MOVING
    if any(abs(m) > config.bound_dps for m in window.mean_dps):
        return BEYOND_BOUND
    return STILL
