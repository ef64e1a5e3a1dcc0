"""One axis's tracker step as a closure over plain floats: what the daemon runs on every frame.

Why: :meth:`~canical.tracking.tracker.BiasTracker.step` keeps its running sums in lists on
objects, so each sample costs a dozen attribute and list accesses (about 0.75 µs); the daemon
steps three trackers per frame. Here the per-sample work (time and power-on, the window's sums,
the slew) runs on the closure's own floats, and the tracker is called only where something is
decided (:meth:`~BiasTracker.close_window`, :meth:`~BiasTracker.power_on`), with the state
handed over (:meth:`~BiasTracker.resume`) and taken back (:meth:`~BiasTracker.step_state`) as a
:class:`~canical.tracking.tracker.StepState`, so the tracker decides exactly as when stepped itself.
The floating-point operations are the tracker's, in its order: the output is the same, bit for bit
(``tests/tracking/test_fast_step.py``), and the offline replay uses this too.

The tracker object is current only after :attr:`FastStep.sync` (status pages, saving the state).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

from canical.tracking.tracker import POWER_ON_STEP_S, BiasTracker, StepState

NAN = math.nan


@dataclass(frozen=True)
class FastStep:
    """``step(t_s, rate, temp_c, cue)`` returns the bias to subtract; ``applied()`` is the bias
    applied now (for a sample that is not stepped); ``sync()`` brings the tracker up to date."""

    step: Callable[[float, float, float, float | None], float]
    applied: Callable[[], float]
    sync: Callable[[], None]


def fast_step(tracker: BiasTracker) -> FastStep:
    """The step of a one-axis tracker (ValueError for more axes), continuing from its state."""
    if len(tracker.axes) != 1:
        raise ValueError(f"fast_step steps one axis, the tracker has {len(tracker.axes)}")
    cfg = tracker.config
    window_s, slew_rate, below = cfg.window_s, cfg.slew_dps_per_s, cfg.cue_threshold
    at = tracker.step_state()
    last_t, temp = at.last_t, at.temp_c
    n, start, temp_sum, cue_moving = at.n, at.start_s, at.temp_sum, at.cue_moving
    (ref,), (s1,), (s2,) = at.ref, at.s1, at.s2
    (applied,), (target,), settled = at.applied, at.target, at.settled

    def push() -> None:
        """The closure's state into the tracker, as if it had stepped itself."""
        tracker.resume(StepState(last_t, temp, n, start, temp_sum, cue_moving, (ref,), (s1,), (s2,),
                                 (applied,), (target,), settled))

    def pull() -> None:
        """What a decision changed: the window restarts, the target may move."""
        nonlocal n, target, settled
        now = tracker.step_state()
        n, (target,), settled = now.n, now.target, now.settled

    def step(t_s: float, r: float, temp_c: float = NAN, cue: float | None = None) -> float:
        nonlocal last_t, temp, n, start, temp_sum, cue_moving, ref, s1, s2, applied, settled
        last = last_t
        if t_s < last:
            if t_s < last - POWER_ON_STEP_S:
                push()
                tracker.power_on()
                pull()
                last = NAN
            else:  # jitter: time does not run back within a power-on
                t_s = last
        if temp_c == temp_c:
            temp = temp_c
        if n == 0:
            ref, s1, s2, n, start, temp_sum, cue_moving = r, 0.0, 0.0, 0, t_s, 0.0, False
        d = r - ref
        s1 += d
        s2 += d * d
        n += 1
        temp_sum += temp
        if below is not None and not (cue is not None and -below < cue < below):
            cue_moving = True
        if t_s - start >= window_s:
            push()
            tracker.close_window(t_s)
            pull()
        if last != last:
            applied, settled = target, True
        elif not settled:
            limit = slew_rate * (t_s - last)
            delta = target - applied
            if delta > limit:
                applied += limit
            elif delta < -limit:
                applied -= limit
            else:
                applied, settled = target, True
        last_t = t_s
        return applied

    def applied_now() -> float:
        return applied

    return FastStep(step, applied_now, push)


Bias3 = tuple[float, float, float]


@dataclass(frozen=True)
class FastStep3:
    """:class:`FastStep` for one tracker over three axes (an IMU set: a standstill is the
    vehicle's): ``step(t_s, r0, r1, r2, temp_c, cue)`` returns the three biases to subtract."""

    step: Callable[[float, float, float, float, float, float | None], Bias3]
    applied: Callable[[], Bias3]
    sync: Callable[[], None]


def fast_step3(tracker: BiasTracker) -> FastStep3:
    """The step of a three-axis tracker (ValueError for another count), continuing from its state.

    :func:`fast_step` written out for three axes: the same operations in the tracker's order
    (each axis's sums, one window for all, each axis's slew and one ``settled`` for all)."""
    if len(tracker.axes) != 3:
        raise ValueError(f"fast_step3 steps three axes, the tracker has {len(tracker.axes)}")
    cfg = tracker.config
    window_s, slew_rate, below = cfg.window_s, cfg.slew_dps_per_s, cfg.cue_threshold
    at = tracker.step_state()
    last_t, temp = at.last_t, at.temp_c
    n, start, temp_sum, cue_moving = at.n, at.start_s, at.temp_sum, at.cue_moving
    (ref0, ref1, ref2), (s10, s11, s12), (s20, s21, s22) = at.ref, at.s1, at.s2
    a0, a1, a2 = at.applied
    g0, g1, g2 = at.target
    settled = at.settled

    def push() -> None:
        """The closure's state into the tracker, as if it had stepped itself."""
        tracker.resume(StepState(last_t, temp, n, start, temp_sum, cue_moving, (ref0, ref1, ref2),
                                 (s10, s11, s12), (s20, s21, s22), (a0, a1, a2), (g0, g1, g2), settled))

    def pull() -> None:
        """What a decision changed: the window restarts, the target may move."""
        nonlocal n, g0, g1, g2, settled
        now = tracker.step_state()
        n, settled = now.n, now.settled
        g0, g1, g2 = now.target

    def step(t_s: float, r0: float, r1: float, r2: float, temp_c: float = NAN,
             cue: float | None = None) -> Bias3:
        nonlocal last_t, temp, n, start, temp_sum, cue_moving, ref0, ref1, ref2, s10, s11, s12
        nonlocal s20, s21, s22, a0, a1, a2, settled
        last = last_t
        if t_s < last:
            if t_s < last - POWER_ON_STEP_S:
                push()
                tracker.power_on()
                pull()
                last = NAN
            else:  # jitter: time does not run back within a power-on
                t_s = last
        if temp_c == temp_c:
            temp = temp_c
        if n == 0:
            ref0, ref1, ref2, n, start, temp_sum, cue_moving = r0, r1, r2, 0, t_s, 0.0, False
            s10 = s11 = s12 = s20 = s21 = s22 = 0.0
        d = r0 - ref0
        s10 += d
        s20 += d * d
        d = r1 - ref1
        s11 += d
        s21 += d * d
        d = r2 - ref2
        s12 += d
        s22 += d * d
        n += 1
        temp_sum += temp
        if below is not None and not (cue is not None and -below < cue < below):
            cue_moving = True
        if t_s - start >= window_s:
            push()
            tracker.close_window(t_s)
            pull()
        if last != last:
            a0, a1, a2, settled = g0, g1, g2, True
        elif not settled:
            limit = slew_rate * (t_s - last)
            settled = True
            delta = g0 - a0
            if delta > limit:
                a0 += limit
                settled = False
            elif delta < -limit:
                a0 -= limit
                settled = False
            else:
                a0 = g0
            delta = g1 - a1
            if delta > limit:
                a1 += limit
                settled = False
            elif delta < -limit:
                a1 -= limit
                settled = False
            else:
                a1 = g1
            delta = g2 - a2
            if delta > limit:
                a2 += limit
                settled = False
            elif delta < -limit:
                a2 -= limit
                settled = False
            else:
                a2 = g2
        last_t = t_s
        return a0, a1, a2

    def applied_now() -> Bias3:
        return a0, a1, a2

    return FastStep3(step, applied_now, push)
