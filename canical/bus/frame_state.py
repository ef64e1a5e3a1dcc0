"""What the raw frame's path keeps between frames, and the plan it corrects a generation of sets by.

Why a record of its own: the reference handler (:mod:`.reference_handler`) and the generated one
(:mod:`.frame_handler`) take turns on the raw frame (the generated one hands a frame over when
the sets are not its own), so the counters, the held inputs and the statistics they carry on
must be one state both own, not the daemon's private attributes each writes.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from canical.bus.active_sets import ActiveSets
from canical.bus.bias_tracking import DaemonTracking
from canical.bus.frame_handler import NO_PLAN, CompiledAxes, FrameLayout, Plan, plan_for
from canical.bus.status import Stats

__all__ = ["FrameCounters", "FrameState", "Plans"]


@dataclass(slots=True)
class FrameCounters:
    """The rolling counters: the raw frame's last (None: none yet), the rate frame's next."""

    prev: int | None = None
    tx: int = 0


@dataclass(slots=True)
class FrameState:
    """The frame path's state: counters, each input's latest value and the time it came, the
    latest bytes of the messages an own layout re-encodes, and the statistics."""

    stats: Stats
    counters: FrameCounters = field(default_factory=FrameCounters)
    values: dict[str, float] = field(default_factory=dict)
    times: dict[str, float] = field(default_factory=dict)
    held_frames: dict[int, bytes] = field(default_factory=dict)

    def restart(self) -> None:
        """As at start: no input held, the counters from the beginning (the statistics stay)."""
        self.counters.prev, self.counters.tx = None, 0  # in place: generated handlers hold it
        self.values.clear()
        self.times.clear()
        self.held_frames.clear()


class Plans:
    """The plan of the sets in use (:func:`~canical.bus.frame_handler.plan_for`), built on the
    first frame of each generation of sets; the bias tracking follows the sets."""

    def __init__(self, layout: FrameLayout, max_age: dict[str, float], tracking: DaemonTracking | None, *,
                 compiled: bool) -> None:
        self.layout, self.max_age, self.tracking, self.compiled = layout, max_age, tracking, compiled
        #: Per corrector, its compiled function (kept with the corrector across reloads).
        self.compiled_axes: CompiledAxes = CompiledAxes()
        self.current: Plan = NO_PLAN

    def plan(self, sets: ActiveSets) -> Plan:
        plan = self.current
        if plan.sets is sets:
            return plan
        self.current = plan = plan_for(sets, self.layout, self.max_age, self.compiled_axes,
                                       compiled=self.compiled)
        if self.tracking is not None:
            self.tracking.for_sets(sets.combined_id, tuple(ax.axis for ax in sets.axes),
                                   tuple(None if ax.corrector is None else ax.corrector.cset.fit
                                         for ax in sets.axes),
                                   joint=sets.coupling is not None and sets.complete,
                                   sensor=next((ax.corrector.cset.sensor_id for ax in sets.axes
                                                if ax.corrector is not None), ""))
        return plan

    def forget(self) -> None:
        """Compile and plan again from the next frame (a fresh start, as the benchmark makes)."""
        self.compiled_axes = CompiledAxes()
        self.current = NO_PLAN
