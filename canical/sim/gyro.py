"""A single-axis MEMS gyro model, output in raw counts.

The scale factor is nonlinear the way real parts are: a smooth difference
between positive and negative rates (drive/sense asymmetry), plus quadratic and
cubic terms from structure and electronics, plus a gentle ripple. Dynamics are a
first-order low-pass (the sensor's bandwidth); output is noisy, quantised and
clipped at the converter's rails.

Noise is given by the terms of an Allan-deviation plot, each switchable (0 = off):

* angle random walk — white rate noise, ``noise_dps`` per sample (N in
  deg/s/√Hz is ``noise_dps / sqrt(fs)``; Allan σ(τ) = N/√τ);
* bias instability — flicker (1/f) bias, ``bias_instability_dps`` = B, the
  Allan floor σ ≈ 0.664·B; made as a sum of Gauss-Markov processes, one per
  decade of correlation time from 0.1 s to 10⁵ s, each of variance B²·ln10/(2π),
  which sums to the 1/f spectrum B²/(2πf) over that band;
* rate random walk — ``rate_random_walk_dps_rt_s`` = K in (deg/s)/√s, a bias
  that random-walks (Allan σ(τ) = K·√(τ/3));
* quantisation — the converter's step ``lsb`` in counts (Allan σ(τ) = √3·Q/τ
  with Q = lsb/(sensitivity·√12) in deg/s·s at unit sample time); 0 = no rounding.

Effects the calibrator is not told about (temperature, warm-up, supply,
direction...) plug in as :class:`Effect` objects: each adds a rate error and a
relative scale-factor error computed from the time, the true rate and the
auxiliary channels of the environment.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Protocol

import numpy as np
from scipy.signal import lfilter


class Effect(Protocol):
    """Something the sensor does that the declared model does not know about."""

    def errors(
        self, time_s: np.ndarray, rate_dps: np.ndarray, aux: dict[str, np.ndarray]
    ) -> tuple[np.ndarray, np.ndarray]:
        """(additive rate error in deg/s, relative scale-factor error) per sample."""
        ...


@dataclass(frozen=True)
class GyroModel:
    """Parameters of the simulated sensor."""

    sensitivity: float = 400.0  # counts per deg/s
    bias_counts: float = 37.0  # zero bias V0
    asymmetry: float = 0.03  # relative scale difference, positive vs negative rates
    asymmetry_width_dps: float = 6.0  # how smoothly the asymmetry sets in around 0
    quadratic: float = 0.015  # relative ΔV error at full scale, even part
    cubic: float = -0.035  # relative ΔV error at full scale, odd part
    ripple: float = 0.0  # relative sinusoidal nonlinearity
    ripple_period_dps: float = 40.0
    full_scale_dps: float = 60.0
    noise_dps: float = 0.08  # white noise per sample (angle random walk), deg/s rms
    bias_instability_dps: float = 0.0  # flicker floor B (Allan minimum ≈ 0.664·B)
    rate_random_walk_dps_rt_s: float = 0.0  # K, (deg/s)/√s
    bandwidth_hz: float = 40.0
    lsb: float = 1.0  # quantisation step, counts
    rail_counts: float = 32767.0
    #: An output stage that compresses as it nears its limit: ΔV becomes ΔV/(1+|ΔV/A|^p)^(1/p),
    #: A = ``compression_counts`` (None: no compression), p = ``compression_sharpness`` (the
    #: larger, the later and sharper the knee). With A a little beyond ``rail_counts`` the sensor
    #: bends sharply in the last rates before it clips.
    compression_counts: float | None = None
    compression_sharpness: float = 6.0
    effects: tuple[Effect, ...] = field(default_factory=tuple)

    def transfer(self, rate_dps: np.ndarray) -> np.ndarray:
        """Static ΔV(ω) in counts, without noise: the curve calibration must invert."""
        w = np.asarray(rate_dps, dtype=float)
        x = w / self.full_scale_dps
        shape = (
            w * (1.0 + self.asymmetry * np.tanh(w / self.asymmetry_width_dps))
            + self.full_scale_dps * (self.quadratic * x**2 + self.cubic * x**3)
            + self.full_scale_dps * self.ripple * np.sin(2 * np.pi * w / self.ripple_period_dps)
        )
        return self.compressed(self.sensitivity * shape)

    def compressed(self, dv: np.ndarray) -> np.ndarray:
        """ΔV through the output stage's compression near its limit (unchanged without one)."""
        if self.compression_counts is None:
            return dv
        p = self.compression_sharpness
        return dv / (1.0 + np.abs(dv / self.compression_counts) ** p) ** (1.0 / p)

    def output(
        self,
        time_s: np.ndarray,
        rate_dps: np.ndarray,
        *,
        aux: dict[str, np.ndarray] | None = None,
        rng: np.random.Generator | None = None,
        fs_hz: float | None = None,
        noise_dps: np.ndarray | None = None,
    ) -> np.ndarray:
        """Raw counts for a table rate history.

        ``noise_dps`` is the sensor's noise per sample (deg/s) to use instead of drawing it
        from ``rng``: the same sensor can then be recorded on two tables with the same noise
        at the same instants of each plateau (:mod:`canical.sim.paired_noise`).
        """
        rng = rng if rng is not None else np.random.default_rng(0)
        aux = aux or {}
        w = np.asarray(rate_dps, dtype=float)
        if fs_hz is None:
            fs_hz = 1.0 / float(np.median(np.diff(time_s))) if len(time_s) > 1 else 200.0
        alpha = 1.0 - np.exp(-2 * np.pi * self.bandwidth_hz / fs_hz)
        sensed = lfilter([alpha], [1.0, alpha - 1.0], w, zi=[w[0] * (1 - alpha)])[0] if len(w) else w
        bias = np.zeros_like(w)
        scale = np.ones_like(w)
        for effect in self.effects:
            b, s = effect.errors(time_s, sensed, aux)
            bias = bias + b
            scale = scale * (1.0 + s)
        dv = self.transfer(sensed) * scale + self.sensitivity * bias
        if noise_dps is None:
            noise_dps = self.noise(len(w), fs_hz, rng)
        dv = dv + self.sensitivity * np.asarray(noise_dps, dtype=float)
        raw = self.bias_counts + dv
        if self.lsb > 0:
            raw = np.round(raw / self.lsb) * self.lsb
        return np.clip(raw, -self.rail_counts - 1, self.rail_counts)

    def noise(self, n: int, fs_hz: float, rng: np.random.Generator) -> np.ndarray:
        """All the sensor's noise, deg/s per sample: white (angle random walk) plus coloured."""
        return self.noise_dps * rng.standard_normal(n) + self.coloured_noise(n, fs_hz, rng)

    def coloured_noise(self, n: int, fs_hz: float, rng: np.random.Generator) -> np.ndarray:
        """Bias instability plus rate random walk, deg/s per sample (zeros when both are off)."""
        out = np.zeros(n)
        dt = 1.0 / fs_hz
        if self.bias_instability_dps > 0 and n:
            variance = self.bias_instability_dps**2 * np.log(10.0) / (2 * np.pi)
            for tau_c in 10.0 ** np.arange(-1, 6):
                a = np.exp(-dt / tau_c)
                drive = np.sqrt(variance * (1 - a * a)) * rng.standard_normal(n)
                start = np.sqrt(variance) * rng.standard_normal()
                out += lfilter([1.0], [1.0, -a], drive, zi=[a * start])[0]
        if self.rate_random_walk_dps_rt_s > 0:
            out += np.cumsum(self.rate_random_walk_dps_rt_s * np.sqrt(dt) * rng.standard_normal(n))
        return out
