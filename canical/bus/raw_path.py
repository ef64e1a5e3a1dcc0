"""Which handler takes the raw frame: the generated one for the sets in use, or the reference.

Built once per generation of sets and of links (a reload, a reconnect): the generated handler
(:func:`~canical.bus.frame_handler.generate_raw_handler`) where it can be, else the reference
handler (:class:`~canical.bus.reference_handler.ReferenceHandler`): an axis on the reference
path, a rate frame whose signals the codec must reorder, a gateway whose output is down, or
``compiled`` off. Either is called ``handler(data, stamp)`` and works on the same
:class:`~canical.bus.frame_state.FrameState`.
"""

from __future__ import annotations

from dataclasses import dataclass

from canical.bus.active_sets import ActiveSets
from canical.bus.bias_tracking import DaemonTracking
from canical.bus.frame_handler import FrameLayout, RawHandler, generate_raw_handler
from canical.bus.frame_state import FrameState, Plans
from canical.bus.link import Link, Sender
from canical.bus.reference_handler import ReferenceHandler, SetsHolder

__all__ = ["RawPath"]


@dataclass(frozen=True)
class _Built:
    """The handler built for these sets and links."""

    sets: ActiveSets | None
    link: Link | None
    out: Link | None
    handler: RawHandler


class RawPath:
    """The raw frame's handlers and the plans they correct by."""

    def __init__(self, layout: FrameLayout, holder: SetsHolder, state: FrameState, sender: Sender,
                 tracking: DaemonTracking | None, max_age: dict[str, float], *, compiled: bool) -> None:
        self.layout, self.holder, self.state, self.sender = layout, holder, state, sender
        self.tracking, self.compiled = tracking, compiled
        self.plans = Plans(layout, max_age, tracking, compiled=compiled)
        self.reference = ReferenceHandler(layout, self.plans, holder, state, sender, tracking)
        self._built = _Built(None, None, None, self.reference)

    def handler(self, sets: ActiveSets) -> RawHandler:
        """The handler for ``sets`` on the sender's links now."""
        link, out = self.sender.link, self.sender.out
        built = self._built
        if built.sets is sets and built.link is link and built.out is out:
            return built.handler
        self._built = _Built(sets, link, out, self._build(sets, link, out))
        return self._built.handler

    def restart(self) -> None:
        """Forget the plans and handlers, and the frame path's state: as at start (the benchmark
        runs the same stream several times)."""
        self.plans.forget()
        self.state.restart()
        self._built = _Built(None, None, None, self.reference)

    def _build(self, sets: ActiveSets, link: Link | None, out: Link | None) -> RawHandler:
        layout, state = self.layout, self.state
        plan = self.plans.plan(sets)
        own = layout.own
        own_link = out if own is not None and own.gateway else link
        rate = layout.rate
        in_order = rate is None or rate.encode_in_order is not None  # the order generated code sends in
        compiled = self.plans.compiled_axes
        if not (self.compiled and in_order and link is not None and own_link is not None
                and len(sets.axes) == 3
                and all(ax.corrector is None or compiled.get(ax.corrector) is not None for ax in sets.axes)):
            return self.reference
        names = {"stats": state.stats, "values": state.values, "times": state.times,
                 "counters": state.counters, "held_frames": state.held_frames,
                 "encode": None if rate is None else rate.encode_in_order,
                 "send": link.send, "send_own": own_link.send, "send_failed": self.sender.failed}
        return generate_raw_handler(layout, sets, plan, owner=self.holder, general=self.reference,
                                    names=names, tracking=self.tracking)
