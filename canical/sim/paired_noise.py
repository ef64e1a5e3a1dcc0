"""The same sensor noise on any table: noise tied to the instants of each plateau.

Comparing a table behaviour with an ideal table is only fair when it is the *same* sensor
with the *same* noise. Drawing the noise sample by sample does not give that: a table that
ramps takes longer between plateaus, so every later plateau sees a different stretch of the
noise sequence, and one seed's held-out error then scatters by a factor of two with that
draw alone (measured: 0.5-1.8x between ramp and ideal on the same seed, at the same model
size). Here the noise is drawn once on the ideal table's clock (instantaneous steps, plateau
k spanning ``[k·dwell, (k+1)·dwell)``), and every tick of a recorded session that lies on
plateau k takes the ideal noise of the same instant of that plateau. Ticks on a rate change
(which the ideal table does not have) take the noise of the instant the plateau begins plus
fresh white noise, so the coloured part stays continuous.
"""

from __future__ import annotations

import numpy as np

from canical.sim.gyro import GyroModel
from canical.sim.table_recording import Schedule


def plateau_paired_noise(gyro: GyroModel, sched: Schedule, time_s: np.ndarray, *, dwell_s: float,
                         fs_hz: float, seed: int | tuple[int, ...]) -> np.ndarray:
    """The sensor's noise, deg/s, at each tick of ``time_s`` on the table of ``sched``."""
    t = np.asarray(time_s, dtype=float)
    key = [int(x) for x in np.atleast_1d(seed)]
    n_ideal = int(np.ceil(sched.rates.size * dwell_s * fs_hz)) + 1
    ideal = gyro.noise(n_ideal, fs_hz, np.random.default_rng([*key, 0]))
    k = np.clip(np.searchsorted(sched.start, t, side="right") - 1, 0, sched.rates.size - 1)
    into = np.maximum(t - sched.end[k], 0.0)  # seconds into plateau k (0 on its rate change)
    idx = np.clip(np.rint((k * dwell_s + into) * fs_hz).astype(np.int64), 0, n_ideal - 1)
    out = ideal[idx]
    ramp = t < sched.end[k]
    if np.any(ramp):
        fresh = np.random.default_rng([*key, 1]).standard_normal(int(ramp.sum()))
        out = out.copy()
        out[ramp] += gyro.noise_dps * fresh
    return out
