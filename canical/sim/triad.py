"""A simulated gyro triad: three single-axis gyros whose sense axes are coupled.

Each axis is a :class:`canical.sim.gyro.GyroModel` (its own scale, bias and nonlinearity); what
each one senses is a row of the 3×3 ``coupling`` matrix times the true rate vector: the diagonal
is the axis's own scale error, the off-diagonal terms its misalignment and cross-axis
sensitivity (0.4–2 % in :func:`random_triad`). The coupling acts before each axis's
nonlinearity, as it does in the part: the sense element sees the projected rate.

Sessions: :func:`axis_session` turns a single-axis table about one IMU axis (``-x`` for the IMU
mounted upside down); :func:`multi_axis_session` is a three-axis table whose plateaus turn all
axes at once (validation and the demo).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from canical.sessions.triad_session import TriadSession, parse_table_axis
from canical.sim.gyro import GyroModel
from canical.sim.rate_table import step_profile

FULL_SCALE_DPS = 150.0


@dataclass(frozen=True)
class TriadModel:
    """Three gyros and the coupling between their sense axes (sensed = coupling @ true)."""

    gyros: tuple[GyroModel, GyroModel, GyroModel]
    coupling: np.ndarray  # (3, 3)

    def output(self, time_s: np.ndarray, rate_dps: np.ndarray, *, seed: int, fs_hz: float) -> np.ndarray:
        """Raw counts (n, 3) for true rate vectors (n, 3); each axis has its own noise stream."""
        sensed = np.asarray(rate_dps, dtype=float) @ self.coupling.T
        return np.column_stack([
            g.output(time_s, sensed[:, i], rng=np.random.default_rng([seed, i]), fs_hz=fs_hz)
            for i, g in enumerate(self.gyros)])


def random_coupling(rng: np.random.Generator, low: float = 0.004, high: float = 0.02) -> np.ndarray:
    """Off-diagonal terms of magnitude ``low``–``high`` with random signs, diagonal 1 ± 1 %."""
    c = rng.uniform(low, high, (3, 3)) * rng.choice([-1.0, 1.0], (3, 3))
    np.fill_diagonal(c, 1.0 + rng.uniform(-0.01, 0.01, 3))
    return c


def random_gyro(rng: np.random.Generator, noise_dps: float = 0.08) -> GyroModel:
    """One axis with its own sensitivity, bias and nonlinearity, spanning ±150 deg/s."""
    return GyroModel(
        sensitivity=float(rng.uniform(90.0, 110.0)),
        bias_counts=float(rng.uniform(-60.0, 60.0)),
        asymmetry=float(rng.uniform(0.01, 0.03)),
        quadratic=float(rng.uniform(-0.015, 0.015)),
        cubic=float(rng.uniform(-0.035, 0.035)),
        full_scale_dps=FULL_SCALE_DPS,
        noise_dps=noise_dps,
    )


def random_triad(seed: int, *, coupling_low: float = 0.004, coupling_high: float = 0.02,
                 noise_dps: float = 0.08) -> TriadModel:
    """A triad drawn from ``seed``: per-axis nonlinearity and coupling of 0.4–2 % by default."""
    rng = np.random.default_rng([seed, 19])
    gyros = (random_gyro(rng, noise_dps), random_gyro(rng, noise_dps), random_gyro(rng, noise_dps))
    return TriadModel(gyros, random_coupling(rng, coupling_low, coupling_high))


def table_rates(limit_dps: float = FULL_SCALE_DPS) -> np.ndarray:
    """One axis's plateaus: −limit…limit and back, 2 deg/s steps below 10 deg/s (where the
    nonlinearity's asymmetry turns), 10 deg/s steps above, starting and ending at rest.

    Up and back down, so that no rate goes with one time since power-on: a one-way sweep lets
    the closed loop take the nonlinearity for a drift of scale with time.
    """
    pos = np.concatenate([np.arange(2.0, 10.0, 2.0), np.arange(10.0, limit_dps + 1e-9, 10.0)])
    up = np.concatenate([-pos[::-1], [0.0], pos])
    return np.concatenate([[0.0], up, up[::-1][1:], [0.0]])


def axis_session(triad: TriadModel, axis: str, *, rates_dps: np.ndarray | None = None,
                 dwell_s: float = 2.0, fs_hz: float = 200.0, seed: int = 0,
                 sensor: str = "SIM-TRIAD") -> TriadSession:
    """The table turning about IMU axis ``axis`` (``x``, ``-x``...), all three outputs recorded."""
    table_axis = parse_table_axis(axis, "axis_session")
    if table_axis is None:
        raise ValueError("axis_session turns one axis; use multi_axis_session")
    rates = table_rates() if rates_dps is None else np.asarray(rates_dps, dtype=float)
    t, w = step_profile(rates, dwell_s=dwell_s, fs_hz=fs_hz)
    vector = np.zeros((t.size, 3))
    vector[:, table_axis.index] = table_axis.sign * w
    raw = triad.output(t, vector, seed=seed, fs_hz=fs_hz)
    return TriadSession(t, raw, vector, table_axis, {}, {"sensor": sensor}, f"sim-{table_axis.label}")


def multi_axis_rates(n_plateaus: int = 12, limit_dps: float = 120.0, seed: int = 0) -> np.ndarray:
    """Plateau rate vectors (n, 3) for a three-axis table, each axis turning at once (zero first)."""
    rng = np.random.default_rng([seed, 3])
    rates = np.round(rng.uniform(-limit_dps, limit_dps, (n_plateaus, 3)))
    return np.vstack([np.zeros((1, 3)), rates])


def multi_axis_session(triad: TriadModel, rates_dps: np.ndarray, *, dwell_s: float = 2.0,
                       fs_hz: float = 200.0, seed: int = 0, sensor: str = "SIM-TRIAD") -> TriadSession:
    """A three-axis table through plateaus of rate vectors: all axes ramp together, then dwell."""
    rates = np.asarray(rates_dps, dtype=float)
    knots = np.vstack([np.zeros((1, 3)), rates])  # from rest, then each plateau in turn
    # The programme as a plateau index 0, 1, 2...: every change takes as long as the largest one
    # takes at 100 deg/s², all axes ramping together.
    ramp_s = _largest_step(knots) / 100.0
    t, index = step_profile(np.arange(1.0, knots.shape[0]), dwell_s=dwell_s, fs_hz=fs_hz,
                            accel_dps2=1.0 / ramp_s)
    steps = np.arange(knots.shape[0], dtype=float)
    vector = np.column_stack([np.interp(index, steps, knots[:, j]) for j in range(3)])
    raw = triad.output(t, vector, seed=seed, fs_hz=fs_hz)
    return TriadSession(t, raw, vector, None, {}, {"sensor": sensor}, "sim-multi")


def _largest_step(knots: np.ndarray) -> float:
    steps = np.abs(np.diff(knots, axis=0))
    return max(float(steps.max()), 1.0)

