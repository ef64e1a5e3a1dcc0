"""A recorded drive replayed row by row through the same step the daemon calls per frame.

Why row by row and not vectorised: the offline output must equal the daemon's bit for bit,
and the only sure way is to run the same code on the same values in the same order.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from canical.tracking.config import TrackerConfig
from canical.tracking.estimate import AxisBias
from canical.tracking.events import StandstillEvent, TakenWindow
from canical.tracking.fast_step import fast_step, fast_step3
from canical.tracking.tracker import BiasTracker


@dataclass(frozen=True)
class Replay:
    """The applied bias per row and axis, and the tracker's events and final state."""

    bias_dps: np.ndarray  # (rows, axes)
    events: tuple[StandstillEvent, ...]
    taken: tuple[TakenWindow, ...]
    learned: tuple[AxisBias, ...]
    power_cycles: int


def replay(time_s: np.ndarray, rates_dps: np.ndarray, config: TrackerConfig, *,
           axes: Sequence[str] = ("z",), temp_c: np.ndarray | None = None, cue: np.ndarray | None = None,
           learned: Sequence[AxisBias] | None = None) -> Replay:
    """Run a tracker over a drive; ``rates_dps`` is (rows,) for one axis or (rows, axes)."""
    rates = np.asarray(rates_dps, dtype=float)
    if rates.ndim == 1:
        rates = rates[:, None]
    tracker = BiasTracker(axes, config, learned)
    out = np.empty(rates.shape)
    times = np.asarray(time_s, dtype=float).tolist()
    rows = rates.tolist()
    temps = np.asarray(temp_c, dtype=float).tolist() if temp_c is not None else [math.nan] * len(times)
    cues = np.asarray(cue, dtype=float).tolist() if cue is not None else [None] * len(times)
    if len(tracker.axes) == 1:  # the daemon's per-frame step (canical.tracking.fast_step)
        fast = fast_step(tracker)
        one = fast.step
        for i, (t, r, temp, c) in enumerate(zip(times, rows, temps, cues, strict=True)):
            out[i, 0] = one(t, r[0], temp, c)
        fast.sync()
    elif len(tracker.axes) == 3:  # an IMU set: the daemon's step over three axes
        fast3 = fast_step3(tracker)
        three = fast3.step
        for i, (t, r, temp, c) in enumerate(zip(times, rows, temps, cues, strict=True)):
            out[i] = three(t, r[0], r[1], r[2], temp, c)
        fast3.sync()
    else:
        step = tracker.step
        for i, (t, r, temp, c) in enumerate(zip(times, rows, temps, cues, strict=True)):
            out[i] = step(t, r, temp, c)
    tracker.finish()
    return Replay(out, tuple(tracker.events), tuple(tracker.taken), tuple(tracker.learned),
                  tracker.power_cycle + 1)
