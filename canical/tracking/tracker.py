"""The bias tracker: one sample per call, the code the daemon runs per frame and the replay per row.

Why one step API: the daemon sees one frame at a time and the offline replay must give the same
output bit for bit, so both call :meth:`BiasTracker.step` and nothing else. Per sample it adds to
running sums and moves the applied bias towards the learned one by at most the slew bound
(O(1)); once per window (:data:`TrackerConfig.window_s`) it decides whether the vehicle stood
still and, if so, takes the window in. Of a run of still windows the last is never used (the
vehicle may have started to move inside it), nor the quiet window before the first (it may hold
the end of braking): they are guards.

Time is time since power-on: when it goes back (by more than a second: less is jitter), the
tracker takes it as a new power-on (the turn-on bias is new, the temperature slope is kept) and
says so in its events.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass

from canical.tracking.config import TrackerConfig
from canical.tracking.estimate import AxisBias
from canical.tracking.events import ADOPTED, REFUSED, PowerOnEvent, StandstillEvent, TakenWindow
from canical.tracking.standstill import (
    BEYOND_BOUND,
    CUE_MOVING,
    STILL,
    WindowStats,
    WindowSums,
    pooled,
    steady,
    verdict,
    window_stats,
)


@dataclass(frozen=True)
class AxisStatus:
    """What a status page shows of one axis."""

    axis: str
    bias_dps: float  # learned, at the current temperature
    sigma_dps: float
    applied_dps: float  # what the output is corrected by now (slewing towards bias_dps)
    age_s: float  # since the last window taken in (NaN: none this power-on)
    updates: int

    def text(self) -> str:
        """For a status line (systemd STATUS, a log): bias, uncertainty, age and updates."""
        age = "not yet this power-on" if math.isnan(self.age_s) else f"{self.age_s:.0f} s ago"
        return (f"{self.axis} bias {self.bias_dps:+.4f}±{self.sigma_dps:.4f} deg/s "
                f"(applied {self.applied_dps:+.4f}), {self.updates} updates, last {age}")


#: Time since power-on going back by more than this is a new power-on; less is timestamp jitter.
POWER_ON_STEP_S = 1.0
#: A steady run is a candidate standstill when a window of it is within this many plausibility
#: bounds on every axis: a little past the bound may be a bias the bound is too tight for, and
#: is shown refused; a steady turn (15 or 95 deg/s) is driving, and is not listed at all.
CANDIDATE_BOUNDS = 3.0


@dataclass(frozen=True)
class StepState:
    """What :meth:`BiasTracker.step` carries from one sample to the next, as plain numbers.

    Why: the daemon's per-frame step (:mod:`canical.tracking.fast_step`) keeps these in local
    floats and hands them over only where the tracker decides something (a window closes, a new
    power-on); this record is that hand-over, so nothing outside reads the tracker's internals.
    """

    last_t: float  # the last sample's time (NaN: none yet this power-on)
    temp_c: float  # the latest temperature reading
    n: int  # samples in the open window
    start_s: float  # the open window's first sample's time
    temp_sum: float
    cue_moving: bool  # the cue said moving (or was missing) in the open window
    ref: tuple[float, ...]  # per axis: the open window's first rate (the sums are about it)
    s1: tuple[float, ...]  # per axis: sum of (rate - ref)
    s2: tuple[float, ...]  # per axis: sum of (rate - ref)²
    applied: tuple[float, ...]  # per axis: the bias subtracted now
    target: tuple[float, ...]  # per axis: the learned bias the applied one slews towards
    settled: bool  # applied == target on every axis


class _Run:
    """The still windows of one standstill so far; the last is pending (a guard until one follows)."""

    def __init__(self, first: WindowStats) -> None:
        self.windows = [first]
        self.accepted = False  # learned from (its mean passed the gate, or it is long enough)
        self.final = 0  # windows before this index are decided
        self.used: list[WindowStats] = []
        self.refused: dict[str, list[WindowStats]] = {CUE_MOVING: [], BEYOND_BOUND: []}

    @property
    def start_s(self) -> float:
        return self.windows[0].start_s


class BiasTracker:
    """Learns each axis's bias at standstills and applies it with a bounded slew."""

    def __init__(self, axes: Sequence[str], config: TrackerConfig,
                 learned: Sequence[AxisBias] | None = None) -> None:
        self.axes = tuple(axes)
        self.config = config
        prior = config.turn_on_sigma_dps**2
        self.learned = [dataclasses.replace(s) for s in learned] if learned is not None else [
            AxisBias(p00=prior, p11=config.temp_slope_sigma**2) for _ in self.axes]
        if len(self.learned) != len(self.axes):
            raise ValueError(f"{len(self.learned)} learned states for {len(self.axes)} axes")
        for state in self.learned:
            state.power_on(config.turn_on_sigma_dps)
        self.applied = [0.0] * len(self.axes)
        self.events: list[StandstillEvent] = []  # the owner may drain these (the daemon logs them)
        self.taken: list[TakenWindow] = []
        self.power_cycle = 0
        self._sums = WindowSums(len(self.axes))
        self._before: WindowStats | None = None
        self._run: _Run | None = None
        self._last_t = math.nan
        self.power_ons: list[PowerOnEvent] = [self._power_on_event()]  # drained like events
        self._temp = config.reference_c
        self._window_s = config.window_s
        self._slew_rate = config.slew_dps_per_s
        self._cue_below = config.cue_threshold
        self._target: list[float] = []
        self._settled = False  # the applied bias has reached the target on every axis
        self._retarget()
        # Until the first sample that can be stepped (the daemon waits for time, temperature and
        # the cue), what was learned before is applied: a restart corrected those frames by 0.
        self.applied[:] = self._target

    # -- per sample ---------------------------------------------------------------------------
    def step(self, t_s: float, rates: Sequence[float], temp_c: float = math.nan,
             cue: float | None = None) -> list[float]:
        """Take one sample; return the bias to subtract from each axis's rate (deg/s).

        The returned list is the tracker's own (read it before the next call). Written for
        the per-frame path: sums and a slew per axis, everything else once per window, the
        target (the learned bias at the latest temperature) too: the cabin warms by a fraction
        of a degree in a window, and the slew takes the step out.
        """
        last = self._last_t
        if t_s < last:
            if t_s < last - POWER_ON_STEP_S:
                self._power_on()
                last = math.nan
            else:  # jitter: time does not run back within a power-on
                t_s = last
        if temp_c == temp_c:  # NaN: no reading, keep the last
            self._temp = temp_c
        sums = self._sums
        if sums.n == 0:
            sums.restart(t_s, rates)
        s1, s2, ref = sums.s1, sums.s2, sums.ref
        for i, r in enumerate(rates):
            d = r - ref[i]
            s1[i] += d
            s2[i] += d * d
        sums.n += 1
        sums.temp_sum += self._temp
        below = self._cue_below
        if below is not None and not (cue is not None and -below < cue < below):
            sums.cue_moving = True  # a missing cue counts as moving; a signed speed's reverse too
        if t_s - sums.start_s >= self._window_s:
            self._close_window(t_s)
            self._retarget()
        applied = self.applied
        if last != last:  # first sample of a power-on: no output yet to step from
            applied[:] = self._target
            self._settled = True
        elif not self._settled:
            limit = self._slew_rate * (t_s - last)
            settled = True
            for i, goal in enumerate(self._target):
                delta = goal - applied[i]
                if delta > limit:
                    applied[i] += limit
                    settled = False
                elif delta < -limit:
                    applied[i] -= limit
                    settled = False
                else:
                    applied[i] = goal
            self._settled = settled
        self._last_t = t_s
        return applied

    def _retarget(self) -> None:
        """The learned bias at the current temperature, per axis: what the output slews towards."""
        h = self._temp - self.config.reference_c
        self._target = [s.b0 + s.slope * h for s in self.learned]
        self._settled = self._target == self.applied

    # -- the step's state, for a step kept outside (canical.tracking.fast_step) ----------------
    def step_state(self) -> StepState:
        """The state :meth:`step` would continue from (a copy)."""
        sums = self._sums
        return StepState(self._last_t, self._temp, sums.n, sums.start_s, sums.temp_sum, sums.cue_moving,
                         tuple(sums.ref), tuple(sums.s1), tuple(sums.s2), tuple(self.applied),
                         tuple(self._target), self._settled)

    def resume(self, state: StepState) -> None:
        """Continue from ``state``, as if :meth:`step` had brought the tracker there.

        The target is not taken: it follows from the learned bias and the temperature, which
        only the tracker changes (:meth:`close_window`, :meth:`power_on`)."""
        if len(state.applied) != len(self.axes):
            raise ValueError(f"a state of {len(state.applied)} axes for a tracker of {len(self.axes)}")
        sums = self._sums
        sums.n, sums.start_s, sums.temp_sum, sums.cue_moving = state.n, state.start_s, state.temp_sum, \
            state.cue_moving
        sums.ref, sums.s1, sums.s2 = list(state.ref), list(state.s1), list(state.s2)
        self._last_t, self._temp, self._settled = state.last_t, state.temp_c, state.settled
        self.applied[:] = state.applied

    def close_window(self, t_s: float) -> None:
        """End the open window at ``t_s`` (what :meth:`step` does once it spans ``window_s``):
        decide on it, then retarget at the latest temperature."""
        self._close_window(t_s)
        self._retarget()

    def power_on(self) -> None:
        """A new power-on (what :meth:`step` does when time goes back by more than
        :data:`POWER_ON_STEP_S`): the standstill under way ends, the turn-on bias is new."""
        self._power_on()

    # -- per window ---------------------------------------------------------------------------
    def _close_window(self, t_s: float) -> None:
        cfg = self.config
        window = window_stats(self._sums, t_s, cfg)
        self._sums.n = 0
        run = self._run
        reference = run.windows[-cfg.steady_windows:] if run else [self._before] if self._before else []
        self._before = window
        if not steady(window, reference, cfg):
            self._end_run()
            return
        if run is None:
            self._run = _Run(window)
            return
        run.windows.append(window)
        if not run.accepted:
            run.accepted = self._acceptable(run)
        if run.accepted:
            self._decide(run, len(run.windows) - 1)

    def _acceptable(self, run: _Run) -> bool:
        """Enough still windows, agreeing with the learned bias or too many to be overruled by it."""
        cfg = self.config
        still = [w for w in run.windows[:-1] if verdict(w, cfg) == STILL]
        if len(still) < cfg.min_run_windows:
            return False
        return len(still) >= cfg.trust_run_windows or self._agrees(still)

    def _agrees(self, still: list[WindowStats]) -> bool:
        cfg = self.config
        temp = sum(w.temp_c for w in still) / len(still)
        for a, state in enumerate(self.learned):
            mean, sigma = pooled(still, a)
            predicted = state.at(temp, cfg.reference_c)
            spread = math.hypot(state.sigma_at(temp, cfg.reference_c), sigma * cfg.window_inflation)
            if abs(mean - predicted) > cfg.k_gate * spread:
                return False
        return True

    def _decide(self, run: _Run, stop: int) -> None:
        """Learn from each undecided window before ``stop`` that passes, count the others refused."""
        for window in run.windows[run.final:stop]:
            why = verdict(window, self.config)
            if why == STILL:
                self._take(window)
                run.used.append(window)
            else:
                run.refused[why].append(window)
        run.final = max(run.final, stop)

    def _take(self, window: WindowStats) -> None:
        cfg = self.config
        before = tuple(s.at(window.temp_c, cfg.reference_c) for s in self.learned)
        for state, mean, sigma in zip(self.learned, window.mean_dps, window.sigma_mean_dps, strict=True):
            state.wander(window.end_s, cfg.bias_walk_dps_rt_s)
            state.take(mean, sigma * cfg.window_inflation, window.temp_c, cfg.reference_c, window.end_s)
        after = tuple(s.at(window.temp_c, cfg.reference_c) for s in self.learned)
        self.taken.append(TakenWindow(window.start_s, window.end_s, self.power_cycle, window.temp_c,
                                      window.mean_dps, before, after))

    def _end_run(self) -> None:
        run = self._run
        if run is None:
            return
        self._run = None
        if self._candidate(run):
            self.events.append(self._event(run))

    def _candidate(self, run: _Run) -> bool:
        """A run of steady windows at a low rate (:data:`CANDIDATE_BOUNDS`), not a steady turn."""
        limit = CANDIDATE_BOUNDS * self.config.bound_dps
        return any(all(abs(m) <= limit for m in w.mean_dps) for w in run.windows)

    def _event(self, run: _Run) -> StandstillEvent:
        cfg = self.config
        refused = run.refused[CUE_MOVING] + run.refused[BEYOND_BOUND]
        shown = run.used or run.windows
        axes = range(len(self.axes))
        mean = tuple(pooled(shown, a)[0] for a in axes)
        sigma = tuple(pooled(shown, a)[1] for a in axes)
        temp = sum(w.temp_c for w in shown) / len(shown)
        if run.used:
            decision = ADOPTED
            reason = f"{len(run.used)} still windows taken in"
            if refused:
                reason += f", {len(refused)} refused"
        else:
            decision = REFUSED
            reason = self._refusal(run, mean)
        return StandstillEvent(
            start_s=run.start_s, end_s=run.windows[-1].end_s, power_cycle=self.power_cycle,
            decision=decision, reason=reason, windows_used=len(run.used),
            windows_refused=len(run.windows) - len(run.used), mean_dps=mean, uncertainty_dps=sigma,
            temp_c=temp, bias_after_dps=tuple(s.at(temp, cfg.reference_c) for s in self.learned))

    def _refusal(self, run: _Run, mean: tuple[float, ...]) -> str:
        cfg = self.config
        verdicts = [verdict(w, cfg) for w in run.windows[:-1]]
        if BEYOND_BOUND in verdicts:
            worst = max(range(len(mean)), key=lambda a: abs(mean[a]))
            return (f"{self.axes[worst]} {mean[worst]:+.3f} deg/s is beyond the plausibility bound "
                    f"±{cfg.bound_dps:g} deg/s: a turn, not a bias")
        if CUE_MOVING in verdicts:
            return f"the cue says moving (not below {cfg.cue_threshold:g})"
        still = verdicts.count(STILL)
        if still >= cfg.min_run_windows:
            return (f"disagrees with the learned bias by more than {cfg.k_gate:g} σ and too short to "
                    f"overrule it ({still} still windows, {cfg.trust_run_windows} would): slow turning?")
        return (f"too short: {len(run.windows)} still windows, the last never used, "
                f"{cfg.min_run_windows} needed")

    def _power_on(self) -> None:
        self._end_run()
        self._sums.n = 0
        self._before = None
        self.power_cycle += 1
        for state in self.learned:
            state.power_on(self.config.turn_on_sigma_dps)
        self.power_ons.append(self._power_on_event())
        self._retarget()

    def _power_on_event(self) -> PowerOnEvent:
        reference = self.config.reference_c
        return PowerOnEvent(self.power_cycle, tuple(s.at(reference, reference) for s in self.learned),
                            tuple(s.sigma_at(reference, reference) for s in self.learned),
                            self._last_t)

    @property
    def time_s(self) -> float:
        """Time since power-on of the latest sample (NaN before the first)."""
        return self._last_t

    # -- at the end, and for a status page -----------------------------------------------------
    def finish(self) -> None:
        """The data ended: a standstill under way is closed (its pending window unused)."""
        self._end_run()

    def status(self) -> list[AxisStatus]:
        cfg = self.config
        now = self._last_t
        return [AxisStatus(axis=a, bias_dps=s.at(self._temp, cfg.reference_c),
                           sigma_dps=s.sigma_at(self._temp, cfg.reference_c), applied_dps=self.applied[i],
                           age_s=now - s.last_update_s, updates=s.updates)
                for i, (a, s) in enumerate(zip(self.axes, self.learned, strict=True))]
