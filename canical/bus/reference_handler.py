"""The raw frame's reference handler: decode, correct each axis, couple, track, encode, send.

Why it stays beside the generated handler (:mod:`.frame_handler`): it is the definition the
generated code is checked against frame for frame, and it handles what that code does not (an
axis on the reference path, the first frames before every input the sets need has come, a rate
frame whose signals the codec must reorder). Both share one interface (``handler(data, stamp)``)
and one state (:class:`~canical.bus.frame_state.FrameState`).
"""

from __future__ import annotations

from math import isfinite
from typing import Any, Protocol

from canical.bus.active_sets import ActiveSets
from canical.bus.bias_tracking import DaemonTracking
from canical.bus.frame_handler import AxisPlan, FrameLayout
from canical.bus.frame_state import FrameState, Plans
from canical.bus.link import Sender
from canical.sets.imu_corrector import couple

__all__ = ["ReferenceHandler", "SetsHolder"]


class SetsHolder(Protocol):
    """Where a handler reads the sets in use, once per frame (the daemon)."""

    @property
    def sets(self) -> ActiveSets: ...


Rates = tuple[float, float, float]
Flags = tuple[bool, bool, bool]
#: The rate frame's fields but its tag and counter: rates, over span, uncalibrated, stale, gap.
RateFields = tuple[float, float, float, bool, bool, bool, bool, bool, bool, bool, bool]


def _correct_axis(axis: AxisPlan, raw: float | None, missing: tuple[str, ...],
                 values: dict[str, float]) -> tuple[float, bool, bool]:
    """One axis's (rate, over its span, uncalibrated): uncalibrated (rate 0) without a set or
    an input its set needs."""
    correct = axis.correct
    if correct is None or raw is None or (missing and any(n in missing for n in axis.needs)):
        return 0.0, False, True
    rate, over = correct(raw, values)
    return rate, over, False


class ReferenceHandler:
    """``handler(data, stamp)``: one raw frame, through cantools or the compiled codecs and each
    axis's ``correct`` as planned."""

    def __init__(self, layout: FrameLayout, plans: Plans, holder: SetsHolder, state: FrameState,
                 sender: Sender, tracking: DaemonTracking | None) -> None:
        self.layout, self.plans, self.holder, self.state = layout, plans, holder, state
        self.sender, self.tracking = sender, tracking

    def __call__(self, data: bytes | bytearray, stamp: float) -> None:
        layout, state = self.layout, self.state
        stats = state.stats
        if len(data) != layout.raw.length:
            stats.bad_length += 1
            return
        signals = layout.raw.values(data)
        stats.frames_in += 1
        values, times = state.values, state.times
        for name, at in layout.raw_inputs_at:
            values[name] = signals[at]
            times[name] = stamp
        gap = self._gap(signals)
        sets = self.holder.sets  # read once: this frame uses exactly this combination
        plan = self.plans.current
        if plan.sets is not sets:
            plan = self.plans.plan(sets)
        missing: tuple[str, ...] = ()
        stale = False
        for name, max_age in plan.ages:
            t = times.get(name)
            if t is None:
                missing, stale = (*missing, name), True
            elif stamp - t > max_age:
                stale = True
        px, py, pz = plan.axes
        # at -1 and not held: an axis absent from the configuration (no raw value, uncalibrated)
        raws = (signals[px.at] if px.at >= 0 else values.get(px.held) if px.held else None,
                signals[py.at] if py.at >= 0 else values.get(py.held) if py.held else None,
                signals[pz.at] if pz.at >= 0 else values.get(pz.held) if pz.held else None)
        rx, ox, ux = _correct_axis(px, raws[0], missing, values)
        ry, oy, uy = _correct_axis(py, raws[1], missing, values)
        rz, oz, uz = _correct_axis(pz, raws[2], missing, values)
        if sets.coupling is not None:  # an IMU set: its axes' rates are coupled, all three or none
            if ux or uy or uz:
                rx, ry, rz, ux, uy, uz = 0.0, 0.0, 0.0, True, True, True
            else:
                rx, ry, rz = couple(sets.coupling, rx, ry, rz)
        if self.tracking is not None:
            rx, ry, rz = self.tracking(stamp, rx, ry, rz, ux, uy, uz)
        if stale:
            stats.stale_frames += 1
        rx, ry, rz = rx if isfinite(rx) else 0.0, ry if isfinite(ry) else 0.0, rz if isfinite(rz) else 0.0
        if layout.own is not None:
            self._send_own(data, raws, (rx, ry, rz), (ux, uy, uz))
        if layout.rate is not None:
            self._send_rate(sets, (rx, ry, rz, ox, oy, oz, ux, uy, uz, stale, gap))
        stats.frames_out += 1

    def _gap(self, signals: tuple[Any, ...]) -> bool:
        """The raw frame's rolling counter skipped (counted); False where it is not checked."""
        at = self.layout.counter_at
        if at is None:
            return False
        counters = self.state.counters
        counter, prev = signals[at], counters.prev
        counters.prev = counter
        if prev is not None and counter != ((prev + 1) & self.layout.counter_mask):
            self.state.stats.counter_gaps += 1
            return True
        return False

    def _send_rate(self, sets: ActiveSets, fields: RateFields) -> None:
        """The rate frame: each rate saturated to its signal's range, the flags, tag and counter.
        (``fields`` one tuple, not one per kind of field: on the reference path, building and
        unpacking those cost more than the send.)"""
        layout = self.layout
        rate = layout.rate
        assert rate is not None
        counters = self.state.counters
        counter = counters.tx
        if rate.encode_in_order is None:
            payload = rate.encode_xyz(*fields, sets.tag, counter)
        else:
            rx, ry, rz = fields[0], fields[1], fields[2]
            (lx, hx), (ly, hy), (lz, hz) = rate.limits
            payload = rate.encode_in_order((lx if rx < lx else hx if rx > hx else rx,
                                            ly if ry < ly else hy if ry > hy else ry,
                                            lz if rz < lz else hz if rz > hz else rz,
                                            *fields[3:], sets.tag, counter))
        counters.tx = (counter + 1) & layout.tx_counter_mask
        self.sender.send(layout.rate_head + payload + layout.rate_pad)

    def _send_own(self, data: bytes | bytearray, raws: tuple[float | None, ...], rates: Rates,
                  flags: Flags) -> None:
        """The own-layout frames: the raw frame (and each other message an axis comes in, from its
        latest frame), each calibrated axis's signal its corrected rate saturated to its range,
        an uncalibrated one's its raw value, the rest as it came."""
        for own in (self.layout.own, *self.layout.own_held):
            assert own is not None
            source = data if own.source_key is None else self.state.held_frames.get(own.source_key)
            if source is None:  # that message has not come yet
                continue
            values = [raws[k] if flags[k] else lo if rates[k] < lo else hi if rates[k] > hi else rates[k]
                      for k, (lo, hi) in zip(own.axes, own.spans, strict=True)]
            self.sender.send(own.head + own.payload(source, values) + own.pad, gateway=own.gateway)
