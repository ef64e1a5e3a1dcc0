"""Auxiliary channels for simulated sessions: temperatures, supply voltage, distractors.

Each factory returns ``f(time_s, rate_dps, rng) -> values``, the form
:func:`canical.sim.sessions.sweep_session` records as an auxiliary column.
Measurement noise is added, as a real channel has it.
"""

from __future__ import annotations

import numpy as np


def temperature_ramp(start_c: float = 20.0, stop_c: float = 50.0, noise_c: float = 0.05):
    """A temperature rising steadily over the session (a chamber ramp, or self-heating)."""

    def f(t, w, rng):
        frac = (t - t[0]) / max(t[-1] - t[0], 1e-9)
        return start_c + (stop_c - start_c) * frac + noise_c * rng.standard_normal(t.size)

    return f


def temperature_warmup(start_c: float = 22.0, rise_c: float = 15.0, tau_s: float = 300.0,
                       noise_c: float = 0.05):
    """Self-heating after power-on: it follows the same law as a warm-up drift (confounded)."""

    def f(t, w, rng):
        return start_c + rise_c * (1 - np.exp(-t / tau_s)) + noise_c * rng.standard_normal(t.size)

    return f


def temperature_steps(levels_c=(-10.0, 5.0, 20.0, 35.0, 50.0), period_s: float = 60.0,
                      noise_c: float = 0.05, seed: int = 0, time_constant_s: float = 5.0):
    """Chamber plateaus at several temperatures in random order, with a thermal lag."""

    def f(t, w, rng):
        order = np.random.default_rng(seed).permutation(np.repeat(levels_c, 1 + int(t[-1] / period_s)))
        target = order[(t // period_s).astype(int) % order.size]
        alpha = 1 - np.exp(-np.median(np.diff(t)) / time_constant_s)
        out = np.empty_like(target)
        acc = target[0]
        for i, x in enumerate(target):
            acc += alpha * (x - acc)
            out[i] = acc
        return out + noise_c * rng.standard_normal(t.size)

    return f


def supply_steps(levels_v=(4.6, 5.0, 5.4), period_s: float = 45.0, noise_v: float = 0.005, seed: int = 1):
    """A supply voltage switched between levels in random order (a bench supply sweep)."""

    def f(t, w, rng):
        order = np.random.default_rng(seed).permutation(np.repeat(levels_v, 1 + int(t[-1] / period_s)))
        return order[(t // period_s).astype(int) % order.size] + noise_v * rng.standard_normal(t.size)

    return f


def white_noise(mean: float = 0.0, sigma: float = 1.0):
    """A channel carrying only noise (a distractor)."""

    def f(t, w, rng):
        return mean + sigma * rng.standard_normal(t.size)

    return f


def random_walk(step: float = 0.05, mean: float = 0.0):
    """A slowly wandering channel unrelated to the sensor (a distractor that can fool a naive test)."""

    def f(t, w, rng):
        return mean + np.cumsum(step * rng.standard_normal(t.size))

    return f


def temperature_cycle(mean_c: float = 25.0, amplitude_c: float = 10.0, periods_s=(410.0, 170.0),
                      noise_c: float = 0.02):
    """A chamber cycling temperature up and down at changing speeds (two incommensurate swings).

    Level and rate of change vary independently: what separates a thermal
    transient (dT/dt) from a temperature level.
    """

    def f(t, w, rng):
        swing = sum(np.sin(2 * np.pi * t / p + k) / (k + 1) for k, p in enumerate(periods_s))
        return mean_c + amplitude_c * swing + noise_c * rng.standard_normal(t.size)

    return f


def temperature_triangle(low_c: float = 15.0, high_c: float = 40.0, ramp_s=(140.0, 220.0, 180.0, 260.0),
                         noise_c: float = 0.02):
    """Heating and cooling ramps between two temperatures, each ramp its own length."""

    def f(t, w, rng):
        edges = np.cumsum(np.resize(np.asarray(ramp_s), 1 + int(t[-1] / min(ramp_s)) + 1))
        k = np.searchsorted(edges, t, side="right")
        start = np.concatenate(([0.0], edges))[k]
        frac = (t - start) / (edges[k] - start)
        up = k % 2 == 0
        level = np.where(up, low_c + (high_c - low_c) * frac, high_c - (high_c - low_c) * frac)
        return level + noise_c * rng.standard_normal(t.size)

    return f


def other_axis_raw(gyro=None, hold_s: float = 7.0, limit_dps: float = 60.0, seed: int = 11):
    """The raw output (counts) of a second axis turned independently (a two-axis table)."""
    from canical.sim.gyro import GyroModel

    gyro = gyro or GyroModel()

    def f(t, w, rng):
        picks = np.random.default_rng(seed).uniform(-limit_dps, limit_dps, 1 + int(t[-1] / hold_s))
        rate = picks[((t - t[0]) // hold_s).astype(int)]
        return gyro.output(t, rate, rng=rng)

    return f


def level_per_plateau(low: float = 0.5, high: float = 8.0, noise: float = 0.02):
    """A level drawn afresh (uniformly over ``low``–``high``) each time the table rate changes:
    a vibration level (g rms) or a load set per plateau, ranging wide and in no order of time."""

    def f(t, w, rng):
        segment = np.concatenate([[0], np.cumsum(np.abs(np.diff(np.asarray(w, dtype=float))) > 1e-9)])
        levels = rng.uniform(low, high, int(segment[-1]) + 1)
        return levels[segment] + noise * rng.standard_normal(t.size)

    return f
