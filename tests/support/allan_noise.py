"""Synthetic gyro rate noise (deg/s) of known IEEE Std 952 terms, for the Allan tests and benchmark.

Each generator follows the defining two-sided spectrum of one term:

* angle random walk: white rate noise of PSD N² (σ² = N²/τ), per-sample deviation N·√fs;
* rate random walk: PSD K²/(2πf)² (σ² = K²τ/3), a random walk with increments K·√dt;
* bias instability: flicker of PSD B²/(2πf) (σ² → 0.664²·B²), white noise shaped by 1/√f.
"""

from __future__ import annotations

import numpy as np

SQRT_HOUR = 60.0


def white_rate(rng: np.random.Generator, n: int, fs: float, arw_deg_rt_h: float) -> np.ndarray:
    return arw_deg_rt_h / SQRT_HOUR * np.sqrt(fs) * rng.standard_normal(n)


def rate_random_walk(rng: np.random.Generator, n: int, fs: float, rrw_deg_h_rt_h: float) -> np.ndarray:
    k = rrw_deg_h_rt_h / (3600.0 * SQRT_HOUR)  # deg/s/√s
    return np.cumsum(k * np.sqrt(1.0 / fs) * rng.standard_normal(n))


def flicker_rate(rng: np.random.Generator, n: int, fs: float, bi_deg_h: float) -> np.ndarray:
    b = bi_deg_h / 3600.0
    f = np.fft.rfftfreq(n, 1.0 / fs)
    one_sided = np.zeros_like(f)
    one_sided[1:] = b**2 / (np.pi * f[1:])  # twice the two-sided B²/(2πf)
    z = rng.standard_normal(f.size) + 1j * rng.standard_normal(f.size)
    return np.fft.irfft(z * np.sqrt(one_sided * fs * n / 4.0), n)  # E|X_k|² = S·fs·n/2


def rrw_for_crossover(arw_deg_rt_h: float, crossover_s: float) -> float:
    """The RRW (deg/h/√h) whose line crosses the ARW line at ``crossover_s`` (N²/τ = K²τ/3)."""
    return np.sqrt(3.0) * arw_deg_rt_h / SQRT_HOUR / crossover_s * 3600.0 * SQRT_HOUR
