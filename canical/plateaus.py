"""Find the constant-rate plateaus of a turntable session.

Only samples taken at a steady, settled table rate say anything about the scale
factor: during a rate change the table's reference and the sensor's output do
not refer to the same instant, and just after it the table overshoots and the
sensor's filter catches up. So a sample enters the fit only when

* the reference rate has been steady (within ``rate_tol``) for a run of samples
  lasting at least ``min_duration_s``, and
* it lies past the run's settling start: ``settle_s`` seconds or
  ``settle_fraction`` of the run, whichever is longer.

Each run is its own plateau, so a session with repeated sweeps gives several
plateaus at the same rate; cross-validation groups and hysteresis both rely on that.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class Plateaus:
    """Per-sample plateau labels and per-plateau summaries."""

    label: np.ndarray  # int per sample: plateau index, or -1 when left out
    rate_dps: np.ndarray  # per plateau: median reference rate
    start: np.ndarray  # per plateau: first used sample index
    stop: np.ndarray  # per plateau: one past the last used sample index
    n_transition: int  # samples at a changing table rate
    n_settling: int  # samples dropped at the start of plateaus

    @property
    def count(self) -> int:
        return int(self.rate_dps.shape[0])

    @property
    def n_used(self) -> int:
        return int(np.sum(self.stop - self.start))


def detect_plateaus(
    time_s: np.ndarray,
    ref_dps: np.ndarray,
    *,
    rate_tol: float = 0.05,
    min_duration_s: float = 1.0,
    settle_s: float = 0.5,
    settle_fraction: float = 0.1,
) -> Plateaus:
    """Label the settled constant-rate samples of a session."""
    ref = np.asarray(ref_dps, dtype=float)
    t = np.asarray(time_s, dtype=float)
    n = ref.shape[0]
    label = np.full(n, -1, dtype=np.int64)
    if n == 0:
        empty = np.zeros(0)
        return Plateaus(label, empty, empty.astype(int), empty.astype(int), 0, 0)
    # A run breaks wherever the reference jumps by more than the tolerance.
    breaks = np.flatnonzero(np.abs(np.diff(ref)) > rate_tol) + 1
    run_starts = np.concatenate(([0], breaks))
    run_stops = np.concatenate((breaks, [n]))
    rates, starts, stops = [], [], []
    n_settling = 0
    for a, b in zip(run_starts, run_stops, strict=True):
        a, b = _steady_tail(ref, int(a), int(b), rate_tol)
        if b - a < 2 or t[b - 1] - t[a] < min_duration_s:
            continue
        settle = max(settle_s, settle_fraction * (t[b - 1] - t[a]))
        first = int(np.searchsorted(t[a:b], t[a] + settle)) + a
        if b - first < 2:
            continue
        n_settling += first - a
        label[first:b] = len(rates)
        rates.append(float(np.median(ref[first:b])))
        starts.append(first)
        stops.append(b)
    n_used = int(np.sum(np.array(stops) - np.array(starts))) if stops else 0
    return Plateaus(
        label=label,
        rate_dps=np.array(rates, dtype=float),
        start=np.array(starts, dtype=np.int64),
        stop=np.array(stops, dtype=np.int64),
        n_transition=n - n_used - n_settling,
        n_settling=n_settling,
    )


def _steady_tail(ref: np.ndarray, a: int, b: int, tol: float) -> tuple[int, int]:
    """Trim the slow-ramp head of a run: keep the tail that stays within ``tol`` of its end."""
    if b - a < 2:
        return a, b
    level = np.median(ref[a + (b - a) // 2 : b])
    off = np.abs(ref[a:b] - level) > tol
    if not off.any():
        return a, b
    return a + int(np.flatnonzero(off)[-1]) + 1, b


def plateau_means(values: np.ndarray, plateaus: Plateaus) -> np.ndarray:
    """Mean of a per-sample array over each plateau's used samples."""
    csum = np.concatenate(([0.0], np.cumsum(values, dtype=float)))
    sums = csum[plateaus.stop] - csum[plateaus.start]
    return sums / (plateaus.stop - plateaus.start)


def plateau_stds(values: np.ndarray, plateaus: Plateaus) -> np.ndarray:
    """Sample standard deviation of a per-sample array over each plateau."""
    mean = plateau_means(values, plateaus)
    sq = plateau_means(values * values, plateaus)
    n = plateaus.stop - plateaus.start
    var = np.maximum(sq - mean * mean, 0.0) * n / np.maximum(n - 1, 1)
    return np.sqrt(var)


def saturated(raw: np.ndarray, plateaus: Plateaus, *, min_fraction: float = 0.01) -> np.ndarray:
    """Per plateau: whether the sensor sat at a rail of its converter.

    A clipped output repeats the session's extreme raw value exactly, many times;
    noise alone almost never does. Such a plateau says nothing about the scale
    factor at its rate (every rate beyond the rail reads the same), so it must
    not be fitted.
    """
    hi, lo = np.max(raw), np.min(raw)
    at_rail = ((raw == hi) | (raw == lo)).astype(float)
    return plateau_means(at_rail, plateaus) >= min_fraction
