"""Effects a real sensor has and the declared model lacks, for the simulator.

Each effect returns (additive rate error in deg/s, relative scale-factor error)
per sample, from the time since power-on, the rate the sensor sees and the
environment's auxiliary channels. The calibrator is never told which are on.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from canical.sets.terms import DirectionTracker, lag_filter


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
class DriftEffect:
    """Bias growing linearly with time since power-on (ageing of a bias over one session)."""

    dps_per_hour: float = 0.3

    def errors(self, time_s, rate_dps, aux):
        return self.dps_per_hour * np.asarray(time_s, dtype=float) / 3600.0, 0.0


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


def _lag(values: np.ndarray, time_s: np.ndarray, tau_s: float) -> np.ndarray:
    """First-order lag of a channel (what a thermal mass does to a temperature)."""
    return lag_filter(np.asarray(values, dtype=float), np.asarray(time_s, dtype=float), tau_s)


@dataclass(frozen=True)
class TemperatureRateEffect:
    """A thermal transient: bias following the rate of change of temperature.

    The die heats before the temperature sensor reads it, so while temperature
    changes the bias carries k·dT/dt, smoothed by the part's thermal mass (a
    first-order lag of ``thermal_tau_s``: causal, as heat flow is). The part was
    already changing at power-on, so the lag starts in step with the first
    seconds' slope rather than at rest.
    """

    channel: str = "temp_c"
    bias_dps_per_c_per_s: float = 1.0
    thermal_tau_s: float = 3.0

    def errors(self, time_s, rate_dps, aux):
        t = np.asarray(time_s, dtype=float)
        v = np.asarray(aux[self.channel], dtype=float)
        first = t - t[0] <= 10.0
        slope0 = float(np.polyfit(t[first], v[first], 1)[0]) if first.sum() > 2 else 0.0
        start = v[0] - self.thermal_tau_s * slope0
        lagged = start + lag_filter(v - start, t, self.thermal_tau_s) - (v[0] - start) * np.exp(
            -(t - t[0]) / self.thermal_tau_s)
        slope = (v - lagged) / self.thermal_tau_s
        return self.bias_dps_per_c_per_s * slope, np.zeros_like(slope)


@dataclass(frozen=True)
class LaggedTemperatureEffect:
    """Bias (and scale) following the temperature the die had τ seconds ago (a lagged reading)."""

    channel: str = "temp_c"
    tau_s: float = 120.0
    reference_c: float = 25.0
    bias_dps_per_c: float = 0.01
    scale_per_c: float = 0.0

    def errors(self, time_s, rate_dps, aux):
        dt = _lag(aux[self.channel], time_s, self.tau_s) - self.reference_c
        return self.bias_dps_per_c * dt, self.scale_per_c * dt


@dataclass(frozen=True)
class LaggedSaturatingEffect:
    """A bias saturating with the temperature the die feels late, A·tanh((lag_τ(T) − centre)/width):
    a smooth function of a channel's lag, in a form on no list."""

    channel: str = "temp_c"
    tau_s: float = 90.0
    amplitude_dps: float = 0.1
    centre_c: float = 25.0
    width_c: float = 8.0

    def shape(self, lagged_c: np.ndarray) -> np.ndarray:
        out: np.ndarray = np.tanh((np.asarray(lagged_c, dtype=float) - self.centre_c) / self.width_c)
        return out

    def errors(self, time_s, rate_dps, aux):
        lagged = _lag(aux[self.channel], time_s, self.tau_s)
        return self.amplitude_dps * self.shape(lagged), np.zeros_like(lagged)


@dataclass(frozen=True)
class SaturatingTransientEffect:
    """A thermal transient that saturates: A·tanh(d/s), d = (T − lag_τ(T))/τ the temperature's rate
    of change smoothed over τ (as a derivative term computes it): a smooth function of a rate
    of change, in a form on no list."""

    channel: str = "temp_c"
    tau_s: float = 3.0
    amplitude_dps: float = 0.08
    scale_c_per_s: float = 0.1

    def shape(self, rate_c_per_s: np.ndarray) -> np.ndarray:
        out: np.ndarray = np.tanh(np.asarray(rate_c_per_s, dtype=float) / self.scale_c_per_s)
        return out

    def errors(self, time_s, rate_dps, aux):
        v = np.asarray(aux[self.channel], dtype=float)
        rate = (v - _lag(v, time_s, self.tau_s)) / self.tau_s
        return self.amplitude_dps * self.shape(rate), np.zeros_like(rate)


@dataclass(frozen=True)
class TemperatureHysteresisEffect:
    """An offset whose sign follows whether temperature last rose or fell (heating vs cooling)."""

    channel: str = "temp_c"
    offset_dps: float = 0.03
    threshold_c: float = 1.0

    def errors(self, time_s, rate_dps, aux):
        tracker = DirectionTracker(self.threshold_c)
        state = np.array([tracker.update(v) for v in np.asarray(aux[self.channel], dtype=float).tolist()])
        return self.offset_dps * state, np.zeros_like(state)


@dataclass(frozen=True)
class CrossAxisEffect:
    """Another axis leaking in: a share of its rate, read from its raw channel (counts)."""

    channel: str = "raw_x"
    coupling: float = 0.004  # deg/s of error per deg/s on the other axis
    other_v0: float = 37.0
    other_sensitivity: float = 400.0

    def errors(self, time_s, rate_dps, aux):
        other = (np.asarray(aux[self.channel], dtype=float) - self.other_v0) / self.other_sensitivity
        return self.coupling * other, np.zeros_like(other)


@dataclass(frozen=True)
class HighRateTemperatureEffect:
    """A temperature scale-factor error that acts only above a rate (a drive loop near its limit).

    Relative scale error k·(T − ref)·max(|ω| − knee, 0)/|ω|: zero below the knee.
    """

    channel: str = "temp_c"
    reference_c: float = 25.0
    scale_per_c: float = 3e-4
    knee_dps: float = 30.0

    def errors(self, time_s, rate_dps, aux):
        w = np.abs(np.asarray(rate_dps, dtype=float))
        gate = np.maximum(w - self.knee_dps, 0.0) / np.maximum(w, 1e-9)
        return np.zeros_like(w), self.scale_per_c * (aux[self.channel] - self.reference_c) * gate


@dataclass(frozen=True)
class RateDependentTemperatureEffect:
    """A scale-factor temperature coefficient that grows smoothly with rate: the nonlinearity's
    shape changes with temperature. Relative scale error k·(T − ref)·s(ω), s = r²/(1 + r²) with
    r = ω/ω_s: nearly nothing at low rate, k·(T − ref) at high rate, no knee anywhere."""

    channel: str = "temp_c"
    reference_c: float = 25.0
    scale_per_c: float = 2e-4
    onset_dps: float = 20.0

    def shape(self, rate_dps: np.ndarray) -> np.ndarray:
        r2 = (np.asarray(rate_dps, dtype=float) / self.onset_dps) ** 2
        out: np.ndarray = r2 / (1.0 + r2)
        return out

    def errors(self, time_s, rate_dps, aux):
        w = np.asarray(rate_dps, dtype=float)
        return np.zeros_like(w), self.scale_per_c * (aux[self.channel] - self.reference_c) * self.shape(w)


@dataclass(frozen=True)
class HiddenVariableEffect:
    """Bias following a variable nobody recorded (humidity, a neighbour's vibration...).

    No candidate can represent it: the loop must say that the residual stays unexplained.
    """

    amplitude_dps: float = 0.06
    period_s: float = 97.0

    def errors(self, time_s, rate_dps, aux):
        t = np.asarray(time_s, dtype=float)
        hidden = np.sin(2 * np.pi * t / self.period_s) * np.sin(2 * np.pi * t / (3.7 * self.period_s))
        return self.amplitude_dps * hidden, np.zeros_like(t)


@dataclass(frozen=True)
class SquareLawEffect:
    """A bias following the square of a channel over its whole range: vibration rectification,
    bias = k·g²rms with the vibration level (g rms) the channel."""

    channel: str = "vib_g"
    bias_dps_per_unit2: float = 0.004

    def errors(self, time_s, rate_dps, aux):
        v = np.asarray(aux[self.channel], dtype=float)
        return self.bias_dps_per_unit2 * v * v, np.zeros_like(v)


@dataclass(frozen=True)
class SaturatingEffect:
    """A bias that saturates with a channel, A·tanh((v − centre)/width): a form on no list."""

    channel: str = "load"
    amplitude_dps: float = 0.12
    centre: float = 4.0
    width: float = 1.2

    def errors(self, time_s, rate_dps, aux):
        v = np.asarray(aux[self.channel], dtype=float)
        return self.amplitude_dps * np.tanh((v - self.centre) / self.width), np.zeros_like(v)
