"""Rate-table motion: constant-rate plateaus joined by constant-acceleration ramps.

A real table cannot jump between rates, so samples during the ramps (and the
sensor's lag after them) are exactly what the plateau detector must leave out.
"""

from __future__ import annotations

import numpy as np


def step_profile(
    rates_dps: np.ndarray,
    *,
    dwell_s: float = 10.0,
    fs_hz: float = 200.0,
    accel_dps2: float = 100.0,
    t0_s: float = 0.0,
) -> tuple[np.ndarray, np.ndarray]:
    """Sample times and table rate for plateaus at ``rates_dps`` in the given order."""
    segments_t: list[np.ndarray] = []
    segments_w: list[np.ndarray] = []
    dt = 1.0 / fs_hz
    t = t0_s
    current = 0.0
    for target in np.asarray(rates_dps, dtype=float):
        ramp_s = abs(target - current) / accel_dps2
        n_ramp = int(np.ceil(ramp_s * fs_hz))
        if n_ramp:
            tt = t + dt * np.arange(n_ramp)
            frac = np.clip((tt - t) / ramp_s, 0.0, 1.0)
            segments_t.append(tt)
            segments_w.append(current + (target - current) * frac)
            t += n_ramp * dt
        n_dwell = round(dwell_s * fs_hz)
        segments_t.append(t + dt * np.arange(n_dwell))
        segments_w.append(np.full(n_dwell, target))
        t += n_dwell * dt
        current = target
    return np.concatenate(segments_t), np.concatenate(segments_w)


def constant_profile(rate_dps: float, n: int, *, fs_hz: float = 200.0, t0_s: float = 0.0):
    """A long record at one rate (the paper's validation test)."""
    return t0_s + np.arange(n) / fs_hz, np.full(n, float(rate_dps))
