"""The median step of a long record, found by counting, is numpy's median of the positive steps."""

from __future__ import annotations

import numpy as np
import pytest

from canical.models import robust_stats


def numpy_median_step(t: np.ndarray, default: float) -> float:
    steps = np.diff(t)
    forward = steps[steps > 0]
    return float(np.median(forward)) if forward.size else default


def clock(kind: int, n: int, rng: np.random.Generator) -> np.ndarray:
    """Timestamps as loggers write them: a decimal clock (steps repeated millions of times, a few
    values apart by rounding), jitter, held and backwards rows, a clock that jumps, a still one."""
    if kind == 0:
        return np.round(np.arange(n) * 0.001, 3)
    if kind == 1:
        return np.cumsum(rng.uniform(0.0005, 0.0015, n))
    if kind == 2:
        return np.cumsum(rng.choice([0.001, 0.002, 0.0, -0.001], n, p=[0.5, 0.3, 0.15, 0.05]))
    if kind == 3:
        return np.cumsum(rng.choice([0.001, 0.0010000001], n))
    if kind == 4:
        return np.concatenate([np.zeros(n // 2), np.cumsum(rng.exponential(1.0, n - n // 2))])
    return np.zeros(n)


@pytest.mark.parametrize("seed", range(4))
@pytest.mark.parametrize("kind", range(6))
def test_counted_median_step_is_numpys(seed: int, kind: int, monkeypatch) -> None:
    monkeypatch.setattr(robust_stats, "COUNTED_ABOVE", 1000)
    monkeypatch.setattr(robust_stats, "STEP_BLOCK", 50_000)
    rng = np.random.default_rng(seed)
    t = clock(kind, int(rng.integers(300_000, 600_000)), rng)
    want = numpy_median_step(t, 0.25)
    assert robust_stats.median_step(t, 0.25) == want
    found, median = robust_stats._median_step_counted(t)
    assert found and (median is None) == (kind == 5)  # counted, not left to the copy


@pytest.mark.parametrize("seed", range(20))
def test_short_or_odd_records_fall_back_to_the_same_median(seed: int, monkeypatch) -> None:
    """Too few steps to sample (or an interval that misses): the copy's median, the same value."""
    monkeypatch.setattr(robust_stats, "COUNTED_ABOVE", 10)
    monkeypatch.setattr(robust_stats, "STEP_BLOCK", 97)
    rng = np.random.default_rng(seed)
    t = clock(seed % 6, int(rng.integers(11, 3000)), rng)
    assert robust_stats.median_step(t, 0.5) == numpy_median_step(t, 0.5)
