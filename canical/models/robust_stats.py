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
    # the deviations are this function's own array: the median may reorder it rather than copy it
    return MAD_TO_SIGMA * float(np.median(np.abs(x - mid), overwrite_input=True))


def median_step(time_s: np.ndarray, default: float) -> float:
    """The rows' typical time step: the median of the positive steps; ``default`` when time never
    advances (a positive median is never 0, so 0.0 as ``default`` also says so)."""
    t = np.asarray(time_s, dtype=float)
    if t.size > COUNTED_ABOVE:
        found, median = _median_step_counted(t)
        if found:
            return default if median is None else median
    forward = positive_steps(t)
    # forward is this function's own copy: the median may reorder it rather than copy it again
    return float(np.median(forward, overwrite_input=True)) if forward.size else default


#: Rows above which the median step is found by counting (two passes over the steps, a block at a
#: time) rather than in a copy of every positive step (a long record's copy is hundreds of MB).
COUNTED_ABOVE = 1 << 20
#: Every this many positive steps one is sampled, to place the median's neighbourhood.
_SAMPLE_EVERY = 64


def _median_step_counted(t: np.ndarray) -> tuple[bool, float | None]:
    """(found, ``np.median`` of the positive steps, None when there is none), in memory bounded by
    a block: a sample of the steps gives a narrow interval the middle rank(s) should fall in; a
    second pass counts the steps below it and at its two ends and keeps those strictly inside (a
    few), among which the rank is taken. Not found (the caller copies every step) when the
    interval missed the rank or holds too many steps; a clock's steps repeated millions of times
    are counted at the interval's ends, never kept."""
    n = 0
    picks = []
    for _, steps in time_steps(t):
        n += int(np.count_nonzero(steps > 0))
        every = steps[::_SAMPLE_EVERY]
        picks.append(every[every > 0])
    if n == 0:
        return True, None
    ranks = [n // 2] if n % 2 else [n // 2 - 1, n // 2]
    sample = np.sort(np.concatenate(picks))
    if not sample.size:
        return False, None
    spread = 4.0 * np.sqrt(sample.size) + 2.0
    lo = float(sample[max(int(ranks[0] / n * sample.size - spread), 0)])
    hi = float(sample[min(int(ranks[-1] / n * sample.size + spread) + 1, sample.size - 1)])
    below = at_lo = at_hi = kept = 0
    inside = []
    for _, steps in time_steps(t):  # lo is positive: a step below it and above 0 is a positive one
        below += int(np.count_nonzero(steps < lo)) - int(np.count_nonzero(steps <= 0))
        at_lo += int(np.count_nonzero(steps == lo))
        if hi > lo:
            at_hi += int(np.count_nonzero(steps == hi))
            inside.append(steps[(steps > lo) & (steps < hi)])
            kept += inside[-1].size
            if kept > n // 16 + STEP_BLOCK:
                return False, None
    middle = np.concatenate(inside) if inside else np.zeros(0)
    values = []
    for rank in ranks:
        r = rank - below
        if r < 0:
            return False, None
        if r < at_lo:
            values.append(lo)
        elif r - at_lo < middle.size:
            values.append(float(np.partition(middle, r - at_lo)[r - at_lo]))
        elif hi > lo and r - at_lo - middle.size < at_hi:
            values.append(hi)
        else:
            return False, None
    # np.median's own last step: the mean of the middle value (or of the two middle values)
    return True, float(np.mean(np.array(values)))


#: Steps taken at a time: a long record's steps are never all made at once beside their copy
#: (half a megabyte: one buffer, made once and in the cache).
STEP_BLOCK = 1 << 16


def time_steps(time_s: np.ndarray) -> Iterator[tuple[int, np.ndarray]]:
    """``np.diff(time_s)`` a block at a time, with the index of each block's first step: the
    same values, in memory bounded by the block. Each block is made in the same buffer: a caller
    keeps what it needs of a block (a copy) before taking the next."""
    t = np.asarray(time_s, dtype=float)
    buffer = np.empty(min(STEP_BLOCK, max(t.size - 1, 0)))
    for a in range(0, t.size - 1, STEP_BLOCK):
        b = min(a + STEP_BLOCK, t.size - 1)
        yield a, np.subtract(t[a + 1 : b + 1], t[a:b], out=buffer[: b - a])


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
