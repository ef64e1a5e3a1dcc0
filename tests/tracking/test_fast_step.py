"""The closure step (what the daemon runs per frame) equals BiasTracker.step bit for bit.

Drives of stops and motion with the awkward parts a vehicle gives: timestamp jitter back in
time, power cycles (time since power-on restarts), temperature readings missing, a cue that
comes and goes, a learned state loaded from a previous run; over many seeds.
"""

from __future__ import annotations

import dataclasses
import itertools
import math

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canical.tracking.config import TrackerConfig
from canical.tracking.estimate import AxisBias
from canical.tracking.fast_step import fast_step, fast_step3
from canical.tracking.tracker import BiasTracker


def drive(seed: int, n: int = 10_000) -> tuple[list[float], list[float], list[float], list[float | None]]:
    rng = np.random.default_rng(seed)
    t, times, rates, temps, cues = 0.0, [], [], [], []
    bias = rng.uniform(-0.4, 0.4)
    moving = False
    for i in range(n):
        if i >= 2000 and rng.random() < 0.001:  # a 20 s stop first: something is always learned
            moving = not moving
        if i >= 2000 and rng.random() < 0.0005:  # a power cycle: time since power-on starts again
            t, bias = rng.uniform(0.0, 2.0), rng.uniform(-0.4, 0.4)
        t += 0.01 if rng.random() > 0.01 else -rng.uniform(0.0, 0.05)  # jitter back, sometimes
        times.append(t)
        rates.append(bias + (rng.normal(0, 20) if moving else 0.0) + rng.normal(0, 0.05))
        temps.append(math.nan if rng.random() < 0.05 else 20.0 + 0.002 * i)
        # moving: a signed speed, forward or in reverse
        cues.append(None if rng.random() < 0.0005 else (rng.choice((5.0, -5.0)) if moving else 0.0))
    return times, rates, temps, cues


def states(tracker: BiasTracker) -> str:
    """Everything a tracker shows, as text (NaN equals NaN there)."""
    learned = tuple(dataclasses.astuple(s) for s in tracker.learned)
    return repr((learned, tuple(tracker.events), tuple(tracker.taken), tracker.power_cycle,
                 tuple(tracker.status())))


@settings(max_examples=12, deadline=None)
@given(seed=st.integers(0, 10_000), cue=st.booleans(), loaded=st.booleans())
def test_the_closure_steps_as_the_tracker_bit_for_bit(seed: int, cue: bool, loaded: bool) -> None:
    times, rates, temps, cues = drive(seed)
    config = TrackerConfig(arw_deg_rt_h=0.3, cue_threshold=0.1 if cue else None)
    learned = [AxisBias(b0=0.2, p00=0.01, slope=0.001, p11=1e-4, updates=7)] if loaded else None
    reference, fast = BiasTracker(("z",), config, learned), BiasTracker(("z",), config, learned)
    step = fast_step(fast)
    for i, (t, r, temp, c) in enumerate(zip(times, rates, temps, cues, strict=True)):
        want = reference.step(t, [r], temp, c)[0]
        got = step.step(t, r, temp, c)
        assert math.copysign(1.0, got) == math.copysign(1.0, want) and got == want, i
        if i % 997 == 0:  # a status page in between changes nothing
            step.sync()
            assert states(fast) == states(reference)
    step.sync()
    assert states(fast) == states(reference)
    assert step.applied() == reference.applied[0]
    assert reference.learned[0].updates > (7 if loaded else 0)  # windows were taken: decisions ran


def test_only_one_axis() -> None:
    with pytest.raises(ValueError, match="one axis"):
        fast_step(BiasTracker(("x", "y"), TrackerConfig()))


Drive3 = tuple[list[float], list[list[float]], list[float], list[float | None]]


def drive3(seed: int, n: int = 8_000) -> Drive3:
    """:func:`drive` on three axes: each its own bias and noise, moving together."""
    times, rates, temps, cues = drive(seed, n)
    rng = np.random.default_rng(seed + 1)
    offsets = rng.uniform(-0.4, 0.4, 2)
    three = [[r, r * 0.3 + offsets[0] + rng.normal(0, 0.05), -r * 0.2 + offsets[1] + rng.normal(0, 0.05)]
             for r in rates]
    return times, three, temps, cues


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 10_000), cue=st.booleans(), loaded=st.booleans())
def test_the_three_axis_closure_steps_as_the_tracker_bit_for_bit(seed: int, cue: bool, loaded: bool) -> None:
    from canical.tracking.fast_step import fast_step3

    times, rates, temps, cues = drive3(seed)
    config = TrackerConfig(arw_deg_rt_h=0.3, cue_threshold=0.1 if cue else None)
    learned = ([AxisBias(b0=0.1 * k, p00=0.01, slope=0.001, p11=1e-4, updates=7) for k in range(3)]
               if loaded else None)
    axes = ("x", "y", "z")
    reference, fast = BiasTracker(axes, config, learned), BiasTracker(axes, config, learned)
    step = fast_step3(fast)
    adopted = 0
    for i, (t, r, temp, c) in enumerate(zip(times, rates, temps, cues, strict=True)):
        want = tuple(reference.step(t, r, temp, c))
        got = step.step(t, r[0], r[1], r[2], temp, c)
        assert all(math.copysign(1.0, g) == math.copysign(1.0, w) for g, w in zip(got, want, strict=True))
        assert got == want, i
        assert step.applied() == want
    step.sync()
    reference.finish()
    fast.finish()
    assert states(fast) == states(reference)
    adopted = sum(e.decision == "adopted" for e in reference.events)
    assert adopted >= 1  # the drive's first stop is learned: the comparison covered decisions


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 10_000), axes=st.sampled_from([1, 3]),
       cuts=st.lists(st.integers(1, 7_999), max_size=6))
def test_a_drive_replayed_in_blocks_gives_the_whole_drives_bias_bit_for_bit(seed: int, axes: int,
                                                                            cuts: list[int]) -> None:
    """Any cut of a drive into blocks (``Replayer.feed``) gives what one ``replay`` of it gives:
    the same bias on every row, the same events and final state."""
    from canical.tracking.replay import Replayer, replay

    times, rates, temps, cues = drive3(seed)
    names = ("x", "y", "z") if axes == 3 else ("z",)
    r = np.array(rates)[:, :axes]
    t, temp = np.array(times), np.array(temps)
    cue = np.array([np.nan if c is None else c for c in cues])
    config = TrackerConfig(arw_deg_rt_h=0.3, cue_threshold=0.1)
    whole = replay(t, r, config, axes=names, temp_c=temp, cue=cue)
    replayer = Replayer(config, axes=names)
    edges = [0, *sorted(set(cuts)), len(t)]
    blocks = [replayer.feed(t[a:b], r[a:b], temp[a:b], cue[a:b]) for a, b in itertools.pairwise(edges)]
    end = replayer.finish()
    assert np.array_equal(np.vstack(blocks), whole.bias_dps)
    assert (end.events, end.taken, end.learned, end.power_cycles) == (
        whole.events, whole.taken, whole.learned, whole.power_cycles)
    assert sum(e.decision == "adopted" for e in whole.events) >= 1


@settings(max_examples=8, deadline=None)
@given(seed=st.integers(0, 10_000), cut=st.integers(1, 2999))
def test_resuming_from_its_own_step_state_changes_nothing(seed: int, cut: int) -> None:
    """The hand-over the closure relies on: a tracker resumed from the state it gave (mid-window,
    mid-slew, anywhere) steps on exactly as one left alone."""
    times, rates, temps, cues = drive(seed, 3000)
    config = TrackerConfig(arw_deg_rt_h=0.3, window_s=0.5)
    alone, handed = BiasTracker(("z",), config), BiasTracker(("z",), config)
    for i, (t, r, temp, c) in enumerate(zip(times, rates, temps, cues, strict=True)):
        if i == cut:
            state = handed.step_state()
            handed.resume(state)
            assert handed.step_state() == state or math.isnan(state.last_t)
        assert handed.step(t, [r], temp, c)[0] == alone.step(t, [r], temp, c)[0]
    assert states(handed) == states(alone)


def test_the_step_state_is_a_copy_and_must_fit_the_axes() -> None:
    tracker = BiasTracker(("x", "y", "z"), TrackerConfig())
    tracker.step(0.0, [0.1, 0.2, 0.3])
    state = tracker.step_state()
    tracker.step(0.01, [0.4, 0.5, 0.6])
    assert state.n == 1 and state.ref == (0.1, 0.2, 0.3)  # not moved by the tracker's next step
    assert tracker.step_state().n == 2
    with pytest.raises(ValueError, match="3 axes for a tracker of 1"):
        BiasTracker(("z",), TrackerConfig()).resume(state)


def test_power_on_and_close_window_are_the_steps_decisions() -> None:
    """What the closure calls where the tracker decides: a new power-on ends the window under way
    and counts the cycle; closing a window empties it."""
    tracker = BiasTracker(("z",), TrackerConfig(window_s=1.0))
    for i in range(50):
        tracker.step(i * 0.01, [0.1])
    tracker.close_window(0.5)
    assert tracker.step_state().n == 0
    tracker.step(0.51, [0.1])
    tracker.power_on()
    assert (tracker.power_cycle, tracker.step_state().n) == (1, 0)


def test_a_loaded_bias_is_applied_before_the_first_stepped_sample() -> None:
    """After a restart, frames that come before the cue's (or temperature's) first value are not
    stepped; they were corrected by 0 instead of what was learned before."""
    config = TrackerConfig(arw_deg_rt_h=0.5)
    learned = (AxisBias(b0=0.3, slope=0.01, p00=1e-4, p01=0.0, p11=1e-6, updates=20),)
    tracker = BiasTracker(("z",), config, learned)
    assert tracker.applied == [pytest.approx(0.3)]  # at the reference temperature: the offset
    assert fast_step(tracker).applied() == pytest.approx(0.3)
    fresh = BiasTracker(("z",), config)
    assert fresh.applied == [0.0] and fast_step(fresh).applied() == 0.0
    three = BiasTracker(("x", "y", "z"), config, learned * 3)
    assert fast_step3(three).applied() == pytest.approx((0.3, 0.3, 0.3))
