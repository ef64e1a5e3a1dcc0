"""The bias's jumps within a session are found where they are, and not in noise alone."""

from __future__ import annotations

import numpy as np
import pytest

from canical.closed_loop.drift_steps import MAX_STEPS, change_times, merge_times, step_terms
from canical.sets.term_kinds import spline_values


def _plateaus(n: int, rng: np.random.Generator) -> tuple[np.ndarray, np.ndarray]:
    """Plateau times (about 10 s apart, jittered) and white noise of 1 unit."""
    t = np.cumsum(rng.uniform(8.0, 12.0, n))
    return t, rng.standard_normal(n)


@pytest.mark.parametrize("seed", range(20))
def test_jumps_of_the_bias_are_found_between_the_right_plateaus(seed: int) -> None:
    rng = np.random.default_rng([seed, 61])
    t, y = _plateaus(80, rng)
    n_jumps = int(rng.integers(1, MAX_STEPS + 1))
    at = np.sort(rng.choice(np.arange(8, 72, 8), n_jumps, replace=False))
    sizes = rng.choice([-1.0, 1.0], n_jumps) * rng.uniform(10.0, 20.0, n_jumps)  # 7-14 standard errors
    for k, size in zip(at, sizes, strict=True):
        y[k:] += size
    found = change_times(t, y)
    assert len(found) == n_jumps
    assert np.all((np.array(found) > t[at - 1]) & (np.array(found) < t[at]))


@pytest.mark.parametrize("seed", range(20))
def test_noise_alone_has_no_jump(seed: int) -> None:
    t, y = _plateaus(80, np.random.default_rng([seed, 62]))
    assert change_times(t, y) == ()


def test_a_staircase_of_many_changes_yields_at_most_the_bound() -> None:
    t, y = _plateaus(100, np.random.default_rng(63))
    y += 10.0 * (np.arange(100) // 10)  # ten changes: a channel's level, not a shocked sensor
    assert len(change_times(t, y)) == MAX_STEPS


def test_a_slow_drift_bends_and_does_not_jump() -> None:
    t, y = _plateaus(80, np.random.default_rng(64))
    y += 40.0 * np.sin(2 * np.pi * t / 300.0) + 0.05 * t  # a cycling effect and a trend, 40x the noise
    assert change_times(t, y) == ()


def test_a_jump_where_a_channel_jumps_is_the_channels() -> None:
    t, y = _plateaus(80, np.random.default_rng(65))
    y[40:] += 15.0
    channel = 25.0 + 0.05 * np.random.default_rng(66).standard_normal(80)
    assert len(change_times(t, y, (channel,))) == 1
    channel[40:] += 10.0  # the temperature stepped at the same boundary
    assert change_times(t, y, (channel,)) == ()


def test_too_few_plateaus_have_no_jump() -> None:
    assert change_times(np.arange(8.0), np.array([0, 0, 0, 0, 9, 9, 9, 9.0])) == ()


def test_a_step_term_is_nought_before_its_jump_and_one_after() -> None:
    (term,) = step_terms((50.0,), 0.0, 100.0, "session clock")
    assert term.params.knots == (0.0, 50.0, 100.0)
    values = spline_values(term.params.knots, term.params.pieces, np.array([0.0, 49.9, 50.0, 100.0]))
    assert values.tolist() == [0.0, 0.0, 1.0, 1.0]
    assert step_terms((0.0, 100.0), 0.0, 100.0, "session clock") == ()  # a jump at an end is the bias


def test_a_jump_seen_again_at_the_neighbouring_boundary_is_listed_once() -> None:
    """Two comparisons find the same jump a plateau apart: the report lists it once; a jump two
    plateaus away is another jump."""
    assert merge_times((), (329.7,), 30.0) == (329.7,)
    assert merge_times((329.7,), (359.7, 120.0), 30.0) == (120.0, 329.7)
    assert merge_times((329.7,), (389.7,), 30.0) == (329.7, 389.7)
