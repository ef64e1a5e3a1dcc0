"""The state a term keeps between samples, and the stateless gate, one sample or a block at a time.

Apart from :mod:`canical.sets.term_kinds` so that the simulator and the closed loop can use the
same trackers as the run time without the registry, and so that the registry can build them
without importing the term record. Every block form does exactly what its one-sample form does
in a loop, so the corrector's ``correct`` and ``correct_one`` agree sample for sample.
"""

from __future__ import annotations

import math

import numpy as np


def rate_gate(dv: np.ndarray, knee_raw: float) -> np.ndarray:
    """g = max(|ΔV| − k, 0)/|ΔV|: 0 up to the knee, rising towards 1 beyond it.

    Times ΔV (the scale form) this is a hinge, sign(ΔV)·max(|ΔV| − k, 0): continuous
    at the knee, so the knee can be estimated by a smooth search.
    """
    a = np.abs(np.asarray(dv, dtype=float))
    gate: np.ndarray = np.maximum(a - knee_raw, 0.0) / np.maximum(a, knee_raw)
    return gate


def gate_one(dv: float, knee_raw: float) -> float:
    """:func:`rate_gate` for one sample, with the same operations in the same order."""
    a = abs(dv)
    return max(a - knee_raw, 0.0) / max(a, knee_raw)


def direction_state(raw: np.ndarray, threshold: float, state: DirectionTracker | None = None) -> np.ndarray:
    """+1/−1/0 per sample: the direction of the last change of ``raw`` larger than ``threshold``.

    ``state`` carries on a stream from its previous block (fresh when None).
    """
    tracker = state or DirectionTracker(threshold)
    out = np.empty(len(raw))
    for i, v in enumerate(np.asarray(raw, dtype=float).tolist()):
        out[i] = tracker.update(v)
    return out


class DirectionTracker:
    """Hysteresis on the raw signal: flips only after a move of ``threshold`` from the last extreme."""

    __slots__ = ("high", "low", "state", "threshold")

    def __init__(self, threshold: float) -> None:
        self.threshold = float(threshold)
        self.state = 0.0
        self.low = math.inf
        self.high = -math.inf

    def update(self, value: float) -> float:
        if value > self.high:
            self.high = value
        if value < self.low:
            self.low = value
        if self.state <= 0.0 and value - self.low > self.threshold:
            self.state = 1.0
            self.high = value
        elif self.state >= 0.0 and self.high - value > self.threshold:
            self.state = -1.0
            self.low = value
        return self.state


def slope_state(raw: np.ndarray, time_s: np.ndarray, tau_s: float,
                state: SlopeTracker | None = None) -> np.ndarray:
    """Smoothed d(raw)/dt per sample, as :class:`SlopeTracker` computes it one sample at a time.

    ``state`` carries on a stream from its previous block (fresh when None).
    """
    tracker = state or SlopeTracker(tau_s)
    return np.array([tracker.update(r, t) for r, t in zip(raw.tolist(), time_s.tolist(), strict=True)])


class SlopeTracker:
    """Rate of change of the raw output, first-order smoothed with time constant ``tau_s``."""

    __slots__ = ("last_raw", "last_t", "tau", "value")

    def __init__(self, tau_s: float) -> None:
        self.tau = float(tau_s)
        self.value = 0.0
        self.last_raw: float | None = None
        self.last_t = 0.0

    def update(self, raw: float, t: float) -> float:
        if self.last_raw is not None and t > self.last_t:
            dt = t - self.last_t
            alpha = 1.0 - math.exp(-dt / self.tau)
            self.value += alpha * ((raw - self.last_raw) / dt - self.value)
        self.last_raw, self.last_t = raw, t
        return self.value


class ChannelTracker:
    """First-order lag y of a channel (time constant τ, exact for any sample spacing).

    ``derivative`` false: y − reference (a lag term); true: (v − y)/τ, which is dy/dt,
    the channel's rate of change smoothed over τ (a derivative term). For the first τ of
    a stream, y is the plain mean of the samples seen so far: starting from the first
    sample alone would carry that one sample's noise for τ, an exponential decay that
    looks like a warm-up. Block and per-sample paths start alike.
    """

    __slots__ = ("count", "derivative", "last_t", "reference", "start_t", "tau", "y")

    def __init__(self, tau_s: float, reference: float = 0.0, derivative: bool = False) -> None:
        self.tau = float(tau_s)
        self.reference = float(reference)
        self.derivative = derivative
        self.y: float | None = None
        self.start_t = 0.0
        self.last_t = 0.0
        self.count = 0

    def update(self, value: float, t: float) -> float:
        if self.y is None:
            self.y, self.start_t, self.count = value, t, 1
        elif t - self.start_t < self.tau:
            self.count += 1
            self.y += (value - self.y) / self.count
        elif t > self.last_t:
            self.y += (1.0 - math.exp(-(t - self.last_t) / self.tau)) * (value - self.y)
        self.last_t = t
        return (value - self.y) / self.tau if self.derivative else self.y - self.reference


def lag_filter(values: np.ndarray, time_s: np.ndarray, tau_s: float) -> np.ndarray:
    """The lag y :class:`ChannelTracker` computes, for a whole record (a mean, then a lag).

    Vectorised when the samples after the first τ are evenly spaced (the usual
    case); sample by sample otherwise.
    """
    values = np.asarray(values, dtype=float)
    time_s = np.asarray(time_s, dtype=float)
    if values.size < 2:
        return values.copy()
    k = int(np.searchsorted(time_s - time_s[0], tau_s, side="left"))  # samples in the mean
    k = max(k, 1)
    out = np.empty_like(values)
    out[:k] = np.cumsum(values[:k]) / np.arange(1, k + 1)
    if k == values.size:
        return out
    dt = np.diff(time_s[k - 1 :])
    step = float(np.median(dt))
    if step > 0 and np.all(np.abs(dt - step) <= 1e-6 * step):
        from scipy.signal import lfilter  # here: the daemon (canical serve) must not load scipy

        a = 1.0 - np.exp(-step / tau_s)
        out[k:] = lfilter([a], [1.0, a - 1.0], values[k:], zi=[(1.0 - a) * out[k - 1]])[0]
        return out
    tracker = ChannelTracker(tau_s)
    return np.array([tracker.update(v, t) for v, t in zip(values.tolist(), time_s.tolist(), strict=True)])
