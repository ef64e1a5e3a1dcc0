"""A recorded drive replayed row by row through the same step the daemon calls per frame.

Why row by row and not vectorised: the offline output must equal the daemon's bit for bit,
and the only sure way is to run the same code on the same values in the same order.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from canical.tracking.config import TrackerConfig
from canical.tracking.estimate import AxisBias
from canical.tracking.events import PowerOnEvent, StandstillEvent, TakenWindow
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
    #: A temperature reading came: without one the tracker states the bias at its reference
    #: temperature, which nobody measured, so the report must not show it as a temperature.
    temperature_recorded: bool = True
    power_ons: tuple[PowerOnEvent, ...] = ()  # the start's, then one per power-on seen
    end_s: float = math.nan  # time since power-on of the last row


class Replayer:
    """A drive replayed a block of rows at a time: the tracker and its per-frame step carry from
    one block to the next, so any cut of the drive into blocks gives the bias :func:`replay`
    gives for the whole, bit for bit (``apply --track-bias`` on a file that does not fit memory).
    """

    def __init__(self, config: TrackerConfig, *, axes: Sequence[str] = ("z",),
                 learned: Sequence[AxisBias] | None = None) -> None:
        self.tracker = tracker = BiasTracker(axes, config, learned)
        self._one = fast_step(tracker) if len(tracker.axes) == 1 else None  # the daemon's step
        self._three = fast_step3(tracker) if len(tracker.axes) == 3 else None  # an IMU set's
        self.temperature_recorded = False

    def feed(self, time_s: np.ndarray, rates_dps: np.ndarray, temp_c: np.ndarray | None = None,
             cue: np.ndarray | None = None) -> np.ndarray:
        """The bias per row and axis, (rows, axes), for the next rows of the drive."""
        rates = np.asarray(rates_dps, dtype=float)
        if rates.ndim == 1:
            rates = rates[:, None]
        out = np.empty(rates.shape)
        times = np.asarray(time_s, dtype=float).tolist()
        rows = rates.tolist()
        temps = np.asarray(temp_c, dtype=float).tolist() if temp_c is not None else [math.nan] * len(times)
        self.temperature_recorded |= temp_c is not None and bool(np.isfinite(temp_c).any())
        cues = np.asarray(cue, dtype=float).tolist() if cue is not None else [None] * len(times)
        if self._one is not None:
            one = self._one.step
            for i, (t, r, temp, c) in enumerate(zip(times, rows, temps, cues, strict=True)):
                out[i, 0] = one(t, r[0], temp, c)
        elif self._three is not None:
            three = self._three.step
            for i, (t, r, temp, c) in enumerate(zip(times, rows, temps, cues, strict=True)):
                out[i] = three(t, r[0], r[1], r[2], temp, c)
        else:
            step = self.tracker.step
            for i, (t, r, temp, c) in enumerate(zip(times, rows, temps, cues, strict=True)):
                out[i] = step(t, r, temp, c)
        return out

    def finish(self) -> Replay:
        """The drive has ended: the tracker's events and final state (bias_dps left empty)."""
        for fast in (self._one, self._three):
            if fast is not None:
                fast.sync()
        tracker = self.tracker
        tracker.finish()
        return Replay(np.empty((0, len(tracker.axes))), tuple(tracker.events), tuple(tracker.taken),
                      tuple(tracker.learned), tracker.power_cycle + 1, self.temperature_recorded,
                      tuple(tracker.power_ons), tracker.time_s)


def replay(time_s: np.ndarray, rates_dps: np.ndarray, config: TrackerConfig, *,
           axes: Sequence[str] = ("z",), temp_c: np.ndarray | None = None, cue: np.ndarray | None = None,
           learned: Sequence[AxisBias] | None = None) -> Replay:
    """Run a tracker over a drive; ``rates_dps`` is (rows,) for one axis or (rows, axes)."""
    replayer = Replayer(config, axes=axes, learned=learned)
    bias = replayer.feed(time_s, rates_dps, temp_c, cue)
    return dataclasses.replace(replayer.finish(), bias_dps=bias)
