"""One axis's bias as learned across standstills: an offset per power-on plus a temperature slope.

Why this form: a MEMS gyro's bias is a turn-on value (different at each power-on, the same
all drive long) plus a drift with temperature that is a property of the part and so holds
across power-ons. Each standstill measures the sum at one temperature; stops at different
temperatures separate the two. A two-state Kalman filter does this in closed form with its
uncertainty: state ``b0`` (bias at the reference temperature) and ``slope`` (deg/s/°C), with
``b0`` wandering slowly between stops and reset to the turn-on spread at each power-on.
Runs only at window ends, never per sample.
"""

from __future__ import annotations

import math
from dataclasses import dataclass


@dataclass
class AxisBias:
    """The learned bias of one axis and its covariance (mutable: updated at window ends)."""

    b0: float = 0.0  # bias at the reference temperature, deg/s
    slope: float = 0.0  # deg/s per °C
    p00: float = 0.25  # var(b0)
    p01: float = 0.0  # cov(b0, slope)
    p11: float = 4e-4  # var(slope)
    updates: int = 0  # windows taken in, over all power-ons
    last_update_s: float = math.nan  # time since power-on of the last window taken in
    last_t_s: float = math.nan  # time the covariance was last carried forward to

    def at(self, temp_c: float, reference_c: float) -> float:
        """The learned bias at a temperature."""
        return self.b0 + self.slope * (temp_c - reference_c)

    def sigma_at(self, temp_c: float, reference_c: float) -> float:
        """1σ of :meth:`at`."""
        h = temp_c - reference_c
        return math.sqrt(max(self.p00 + 2.0 * h * self.p01 + h * h * self.p11, 0.0))

    def wander(self, t_s: float, walk_dps_rt_s: float) -> None:
        """Carry the covariance forward to ``t_s``: the bias may have wandered since."""
        if not math.isnan(self.last_t_s) and t_s > self.last_t_s:
            self.p00 += walk_dps_rt_s**2 * (t_s - self.last_t_s)
        self.last_t_s = t_s

    def power_on(self, turn_on_sigma_dps: float) -> None:
        """A new power-on: the offset is anyone's guess within the turn-on spread, the slope stays."""
        self.p00 = turn_on_sigma_dps**2
        self.p01 = 0.0
        self.last_t_s = math.nan
        self.last_update_s = math.nan

    def take(self, mean_dps: float, sigma_dps: float, temp_c: float, reference_c: float, t_s: float) -> None:
        """Take in one window's mean (a measurement of the bias at ``temp_c``)."""
        h = temp_c - reference_c
        ph0 = self.p00 + h * self.p01  # P·Hᵀ
        ph1 = self.p01 + h * self.p11
        s = self.p00 + 2.0 * h * self.p01 + h * h * self.p11 + sigma_dps * sigma_dps
        k0, k1 = ph0 / s, ph1 / s
        innovation = mean_dps - (self.b0 + self.slope * h)
        self.b0 += k0 * innovation
        self.slope += k1 * innovation
        self.p00 -= k0 * ph0
        self.p01 -= k0 * ph1
        self.p11 -= k1 * ph1
        self.updates += 1
        self.last_update_s = t_s
