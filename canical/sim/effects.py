"""Effects a real sensor has and the declared model lacks, for the simulator.

Each effect returns (additive rate error in deg/s, relative scale-factor error)
per sample, from the time since power-on, the rate the sensor sees and the
environment's auxiliary channels. The calibrator is never told which are on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from canical.terms import DirectionTracker


@dataclass(frozen=True)
class TemperatureEffect:
    """Bias and scale factor drifting with a temperature channel (linear and quadratic bias)."""

    channel: str = "temp_c"
    reference_c: float = 25.0
    bias_dps_per_c: float = 0.01
    bias_dps_per_c2: float = 0.0
    scale_per_c: float = 0.0  # relative scale error per degree

    def errors(self, time_s, rate_dps, aux):
        dt = aux[self.channel] - self.reference_c
        return self.bias_dps_per_c * dt + self.bias_dps_per_c2 * dt**2, self.scale_per_c * dt


@dataclass(frozen=True)
class WarmupEffect:
    """Bias (and optionally scale) settling after power-on: A·exp(−t/τ)."""

    amplitude_dps: float = 0.3
    tau_s: float = 200.0
    scale_amplitude: float = 0.0

    def errors(self, time_s, rate_dps, aux):
        decay = np.exp(-np.asarray(time_s) / self.tau_s)
        return self.amplitude_dps * decay, self.scale_amplitude * decay


@dataclass(frozen=True)
class SupplyEffect:
    """Bias and scale sensitivity to the supply voltage."""

    channel: str = "supply_v"
    reference_v: float = 5.0
    bias_dps_per_v: float = 0.2
    scale_per_v: float = 0.0

    def errors(self, time_s, rate_dps, aux):
        dv = aux[self.channel] - self.reference_v
        return self.bias_dps_per_v * dv, self.scale_per_v * dv


@dataclass(frozen=True)
class DirectionEffect:
    """Hysteresis: an offset whose sign follows the direction the rate last moved in."""

    offset_dps: float = 0.05
    threshold_dps: float = 1.0

    def errors(self, time_s, rate_dps, aux):
        tracker = DirectionTracker(self.threshold_dps)
        state = np.array([tracker.update(v) for v in np.asarray(rate_dps, dtype=float).tolist()])
        return self.offset_dps * state, np.zeros_like(state)
