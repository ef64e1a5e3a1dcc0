"""The raw frame's path, prepared once: the frames' layout, a plan per generation of sets, and
the raw frame's handler generated as one function for exactly those sets.

The reference handler (:class:`canical.bus.reference_handler.ReferenceHandler`) walks a plan, calls a
function per axis, per codec and per check; at a few µs per frame those calls and lookups cost
as much as the work. So, per generation of sets (and socket), it is written out here as one
function: the decode's fields as locals, the three axes' corrections inline
(:func:`~canical.sets.fast_corrector.corrector_lines`, the same statements as the compiled
correctors) and an IMU set's coupling (:func:`~canical.sets.imu_corrector.coupling_lines`),
the staleness checks and constants written in, one ``send``. The generated
handler hands a frame to the reference one when the sets are not its own or an input the sets
need has not arrived yet, so both always send the same frames.
"""

from __future__ import annotations

import copy
import logging
import weakref
from collections.abc import Callable
from dataclasses import dataclass
from socket import MSG_DONTWAIT
from typing import Any

from cantools.database.can import Database, Message

from canical.bus.active_sets import ActiveSets
from canical.bus.bias_tracking import DaemonTracking
from canical.bus.daemon_config import DaemonConfig
from canical.bus.socketcan import frame_key
from canical.bus.socketcan_constants import FRAME_HEAD
from canical.frames.codec import RateEncoder, RawDecoder, signal_range
from canical.frames.compiler import NotCompilable, codec_for, decode_lines, encode_lines
from canical.frames.frame_match import FrameMatch, frame_match
from canical.sets.corrector import Corrector
from canical.sets.fast_corrector import CorrectOne, compile_corrector, corrector_lines, why_not, with_state
from canical.sets.imu_corrector import coupling_lines

__all__ = ["NO_PLAN", "AxisPlan", "CompiledAxes", "FrameLayout", "InputFrame", "OwnLayout", "Plan",
           "RawHandler", "frame_layout", "generate_raw_handler", "own_layout", "plan_for"]

log = logging.getLogger("canical.serve")

RawHandler = Callable[[bytes, float], None]
#: Name → signal pairs of a frame: (input name, position of its signal in the decoded tuple).
Positions = tuple[tuple[str, int], ...]


@dataclass(frozen=True, slots=True)
class InputFrame:
    """A frame carrying run-time inputs: its decoder (values in signal order), length, and
    which input each of its signals holds."""

    decode: Callable[[bytes | bytearray], tuple[Any, ...]]
    length: int
    inputs_at: Positions


@dataclass(frozen=True)
class OwnLayout:
    """The corrected frame in the IMU's own layout: the raw frame's bytes, each axis's signal
    replaced by its corrected value (saturated to the signal's range, rounded by the encode as
    cantools does), every other bit copied through as it came.

    Only the axes' signals are encoded (``encode``, of a message holding just them); the rest
    of the frame is the raw frame's bits (``keep``), so no other signal is decoded or encoded."""

    encode: Callable[[Any], bytes]  # the axes' signals alone, values in ``message``'s order
    message: Message  # the raw message with only the axes' signals
    at: tuple[int, ...]  # per signal of ``message``, its position in the raw frame's decode
    spans: tuple[tuple[float, float], ...]  # per signal of ``message``, the range it can carry
    keep: int  # the raw frame's bits (little-endian integer) that are not the axes' signals
    length: int
    head: bytes  # the frame's kernel head: key, length
    pad: bytes  # zeros to the classic frame's 8 data bytes
    frame_id: int
    extended: bool
    gateway: bool  # sent on another bus than the sensor's
    axes: tuple[int, ...] = ()  # per signal of ``message``, the axis (0, 1, 2) whose rate it carries
    #: The SocketCAN key of the message it re-encodes when not the raw frame (an axis's other
    #: message: its latest frame's bytes), else None.
    source_key: int | None = None

    def payload(self, data: bytes | bytearray, values: Any) -> bytes:
        """The frame for the axes' values (in ``message``'s order): the reference path's form."""
        n = self.length
        word = int.from_bytes(self.encode(values), "little") | (int.from_bytes(data, "little") & self.keep)
        return word.to_bytes(n, "little")


def _axes_message(raw_msg: Message, names: tuple[str, ...]) -> Message:
    """The raw message with only the axes' signals (same bits), for encoding them alone."""
    signals = [copy.deepcopy(raw_msg.get_signal_by_name(n)) for n in dict.fromkeys(names)]
    return Message(frame_id=raw_msg.frame_id, name=raw_msg.name, length=raw_msg.length, signals=signals,
                   is_extended_frame=raw_msg.is_extended_frame, strict=False)


def own_layout(config: DaemonConfig, raw_msg: Message, *, compiled: bool) -> OwnLayout | None:
    """The own-layout output of the raw frame's message as configured (None: not sent)."""
    out = config.own_layout
    if out is None:
        return None
    axes = [(a.raw_signal, k) for k, a in enumerate(config.axes)
            if a.held is None and a.raw_signal is not None]
    return _own_for(raw_msg, axes, out.frame_id, out.extended, out.channel is not None, compiled, None)


def held_own_layouts(config: DaemonConfig, db: Database, *, compiled: bool) -> tuple[OwnLayout, ...]:
    """The own-layout outputs of the other messages axes come in (``own_layout.ids``)."""
    out = config.own_layout
    if out is None:
        return ()
    layouts = []
    for name, frame_id, extended in out.held_ids:
        msg = db.get_message_by_name(name)
        axes = [(a.raw_signal, k) for k, a in enumerate(config.axes)
                if a.message == name and a.raw_signal is not None]
        match = frame_match(msg, config.j1939_source)
        layouts.append(_own_for(msg, axes, frame_id, extended, out.channel is not None, compiled,
                                frame_key(match.usual_id, msg.is_extended_frame)))
    return tuple(layouts)


def _own_for(msg: Message, axes: list[tuple[str, int]], frame_id: int, extended: bool, gateway: bool,
             compiled: bool, source_key: int | None) -> OwnLayout:
    """One message's own-layout output: its ``axes`` signals (name, axis index) replaced."""
    by_signal = dict(axes)
    only = _axes_message(msg, tuple(by_signal))
    ones = {s.name: -1 if s.is_signed else (1 << s.length) - 1 for s in only.signals}
    mask = int.from_bytes(only.encode(ones, scaling=False, strict=False), "little")
    order = [s.name for s in msg.signals]
    return OwnLayout(
        encode=codec_for(only, compiled=compiled).encode, message=only,
        at=tuple(order.index(s.name) for s in only.signals),
        spans=tuple(signal_range(msg, s.name) for s in only.signals),
        keep=((1 << (8 * msg.length)) - 1) & ~mask, length=msg.length,
        head=FRAME_HEAD.pack(frame_key(frame_id, extended), msg.length, 0, 0),
        pad=bytes(max(0, 8 - msg.length)), frame_id=frame_id, extended=extended, gateway=gateway,
        axes=tuple(by_signal[s.name] for s in only.signals), source_key=source_key)


@dataclass(frozen=True)
class FrameLayout:
    """The frames the daemon reads and sends, resolved from the DBC and the configuration at start."""

    raw: RawDecoder
    raw_message: Message
    rate: RateEncoder | None  # None: CANICAL_RATE is not sent (the own layout is)
    rate_message: Message | None
    #: The other frames that carry inputs: decoder and (input, signal) pairs, by (id, extended).
    input_frames: dict[tuple[int, bool], tuple[RawDecoder, tuple[tuple[str, str], ...]]]
    #: The same by SocketCAN key, in their per-frame form.
    input_handlers: dict[int, InputFrame]
    raw_key: int  # the raw frame's SocketCAN key (id and extended flag)
    raw_inputs_at: Positions  # inputs the raw frame itself carries
    counter_at: int | None  # the raw frame's rolling counter (None: not checked)
    counter_mask: int  # it wraps at its DBC width
    tx_counter_mask: int  # the rate frame's counter, likewise
    rate_head: bytes  # the rate frame's kernel head: key, length
    rate_pad: bytes  # zeros to the classic frame's 8 data bytes
    own: OwnLayout | None = None  # the corrected frame in the raw frame's layout, if sent
    #: How the raw frame and the input frames are recognised (a J1939 group: by its PGN and source).
    raw_match: FrameMatch | None = None
    input_matches: tuple[tuple[FrameMatch, int], ...] = ()  # each input frame's match, and its key
    #: Axes whose raw signal is in another message: the input their latest value is held under.
    held_axes: tuple[tuple[str, str], ...] = ()
    #: The own layout of those other messages, re-encoded from their latest frames.
    own_held: tuple[OwnLayout, ...] = ()

    @property
    def masked_inputs(self) -> tuple[tuple[FrameMatch, int], ...]:
        """The input frames matched by more than their exact id (J1939 groups)."""
        return tuple((m, key) for m, key in self.input_matches if not m.exact)

    def receive_matches(self) -> list[FrameMatch]:
        """Every frame the daemon reads: the raw frame and the input frames."""
        assert self.raw_match is not None
        return [self.raw_match, *(m for m, _ in self.input_matches)]


def _wrap_mask(message: Message, signal: str) -> int:
    """The mask a rolling counter wraps at: its signal's width in the DBC."""
    return (1 << message.get_signal_by_name(signal).length) - 1


def frame_layout(config: DaemonConfig, db: Database, *, compiled: bool) -> FrameLayout:
    raw_msg = db.get_message_by_name(config.raw_message)
    rate_msg = None if config.rate_message is None else db.get_message_by_name(config.rate_message)
    raw = RawDecoder(raw_msg, compiled=compiled)
    rate = None if rate_msg is None else RateEncoder(rate_msg, compiled=compiled)
    input_frames: dict[tuple[int, bool], tuple[RawDecoder, tuple[tuple[str, str], ...]]] = {}
    matches: dict[tuple[int, bool], FrameMatch] = {}
    for source in config.inputs.values():
        if source.message == raw_msg.name:
            continue
        msg = db.get_message_by_name(source.message)
        key = (msg.frame_id, msg.is_extended_frame)
        decoder, pairs = input_frames.get(key, (RawDecoder(msg, compiled=compiled), ()))
        input_frames[key] = (decoder, (*pairs, (source.name, source.signal)))
        matches[key] = frame_match(msg, config.j1939_source)
    raw_match = frame_match(raw_msg, config.j1939_source)
    counter = config.counter_signal
    return FrameLayout(
        raw=raw, raw_message=raw_msg, rate=rate, rate_message=rate_msg, input_frames=input_frames,
        input_handlers={
            frame_key(matches[key].usual_id, key[1]): InputFrame(
                decoder.values, decoder.length, tuple((n, decoder.index[s]) for n, s in pairs))
            for key, (decoder, pairs) in input_frames.items()
        },
        raw_key=frame_key(raw_match.usual_id, raw.is_extended),
        raw_inputs_at=tuple((s.name, raw.index[s.signal]) for s in config.inputs.values()
                            if s.message == raw_msg.name),
        counter_at=None if counter is None else raw.index[counter],
        counter_mask=0 if counter is None else _wrap_mask(raw_msg, counter),
        tx_counter_mask=0 if rate_msg is None else _wrap_mask(rate_msg, "Counter"),
        rate_head=b"" if rate is None else FRAME_HEAD.pack(frame_key(rate.frame_id, rate.is_extended),
                                                           rate.length, 0, 0),
        rate_pad=b"" if rate is None else bytes(max(0, 8 - rate.length)),
        own=own_layout(config, raw_msg, compiled=compiled),
        raw_match=raw_match,
        input_matches=tuple((m, frame_key(m.usual_id, key[1])) for key, m in matches.items()),
        held_axes=tuple((a.axis, a.held) for a in config.axes if a.held is not None),
        own_held=held_own_layouts(config, db, compiled=compiled),
    )


@dataclass(frozen=True, slots=True)
class AxisPlan:
    """One axis of a generation of sets, as a frame needs it."""

    at: int  # its raw signal's position in the decoded frame (-1: held, from another message, or absent)
    correct: CorrectOne | None  # None: no set, the axis goes out uncalibrated
    needs: tuple[str, ...]  # the inputs its set reads (and its held raw value's)
    held: str | None = None  # the input its raw value is held under, when in another message


@dataclass(frozen=True, slots=True)
class Plan:
    """What a frame needs of one generation of sets (``sets`` None: no plan yet)."""

    sets: ActiveSets | None
    ages: tuple[tuple[str, float], ...]  # each input the sets read, and how old it may get
    axes: tuple[AxisPlan, ...]


NO_PLAN = Plan(None, (), ())
#: Per corrector, its compiled function (None: the reference path); an entry goes with its corrector.
CompiledAxes = weakref.WeakKeyDictionary[Corrector, CorrectOne | None]


def plan_for(sets: ActiveSets, layout: FrameLayout, max_age: dict[str, float], cache: CompiledAxes, *,
             compiled: bool) -> Plan:
    """The inputs with their maximum age, and per axis where its raw signal is, the function that
    corrects it and the inputs it needs.

    Built once per generation of sets (the first frame after a reload), so each frame uses
    the functions of exactly the sets it read. A corrector is compiled once
    (:mod:`canical.sets.fast_corrector`) and keeps its function, and its state, across reloads
    that keep it (``cache``); one with terms the compiler does not know keeps ``correct_one``.
    """
    axes = []
    held = dict(layout.held_axes)
    ages = [(name, max_age[name]) for name in sets.inputs]
    for ax in sets.axes:
        corrector = ax.corrector
        correct: CorrectOne | None = None
        if corrector is not None:
            if corrector not in cache:
                fast = compile_corrector(corrector) if compiled else None
                if fast is None and compiled:
                    log.info("axis %s: %s; correcting with the reference path", ax.axis, why_not(corrector))
                # None for the reference path: its bound method would hold the corrector,
                # and the entry would outlive it (one leaked set per reload).
                cache[corrector] = fast
            correct = cache[corrector] or corrector.correct_one
        name = held.get(ax.axis)
        if ax.raw_signal is None:  # absent from the configuration: never corrected
            axes.append(AxisPlan(-1, None, ()))
            continue
        if name is None:
            axes.append(AxisPlan(layout.raw.index[ax.raw_signal], correct, ax.required_inputs))
            continue
        axes.append(AxisPlan(-1, correct, (*ax.required_inputs, name), name))
        if correct is not None:  # its raw value must have come, and be recent
            ages.append((name, max_age[name]))
    return Plan(sets, tuple(ages), tuple(axes))


@dataclass(frozen=True)
class _Source:
    """The generated function's lines so far and the names they use."""

    lines: list[str]
    ns: dict[str, Any]

    def add(self, lines: list[str], names: dict[str, Any]) -> None:
        self.lines.extend(lines)
        self.ns.update(names)


def generate_raw_handler(layout: FrameLayout, sets: ActiveSets, plan: Plan, *, owner: object,
                         general: RawHandler, names: dict[str, Any],
                         tracking: DaemonTracking | None = None) -> RawHandler:
    """The raw frame's handler for ``sets`` as one generated function.

    ``owner`` holds the sets in use (the code reads its ``sets``), ``general`` is the reference
    handler, ``names`` what else the code uses: the frame path's state (``stats``, ``values``,
    ``times``, ``held_frames`` and ``counters``, whose ``prev`` and ``tx`` it carries on),
    ``encode`` (the rate frame's codec), ``send`` and ``send_own`` (the links') and
    ``send_failed``; ``tracking`` is the bias tracking when it is on. Only for
    three axes on compiled correctors and a rate frame whose signals come in
    :meth:`~canical.frames.codec.RateEncoder.encode_xyz`'s order.
    """
    carried = {name for name, _ in layout.raw_inputs_at}
    awaited = [(name, age) for name, age in plan.ages if name not in carried]
    src = _Source(["def on_raw(data, stamp):", "    if self.sets is not SETS:",
                   "        return general(data, stamp)"],
                  {"self": owner, "SETS": sets, "general": general, "decode": layout.raw.values, **names,
                   "MSG_DONTWAIT": MSG_DONTWAIT, "FRAME": layout.rate_head})
    if awaited:
        src.lines.extend(["    try:",
                          *(f"        t{i} = times[{name!r}]" for i, (name, _) in enumerate(awaited)),
                          "    except KeyError:  # an input the sets need has not come yet",
                          "        return general(data, stamp)"])
    _decode_and_count(src, layout, plan)
    # Each input the sets read, once: the raw frame's own from its fields, the others held.
    held = {name: f"s{at}" for name, at in layout.raw_inputs_at}
    for i, (name, _) in enumerate(awaited):
        src.lines.append(f"    i{i} = values[{name!r}]")
        held[name] = f"i{i}"
    # The raw frame's own inputs are as old as this frame: never stale (max_age_s > 0).
    # Inputs of other frames change only when those arrive: terms of them alone are kept.
    slow, state = frozenset(f"i{i}" for i in range(len(awaited))), list[str]()
    stale = " or ".join(f"stamp - t{i} > {age!r}" for i, (_, age) in enumerate(awaited)) or "False"
    src.lines.append(f"    stale = {stale}")
    flags = []  # the rate frame's axes in the sets' order, as the reference handler: rK, oK, flags[K]
    for k, (ax, axis) in enumerate(zip(sets.axes, plan.axes, strict=True)):
        if ax.corrector is None:  # uncalibrated: rate 0
            src.lines.append(f"    r{k}, o{k} = 0.0, False")
            flags.append("True")
            continue
        raw = f"s{axis.at}" if axis.held is None else held[axis.held]
        src.add(*corrector_lines(ax.corrector, raw, "values", f"r{k}", f"o{k}", tag=f"A{k}_",
                                 held=held, cached=slow, state=state))
        flags.append("False")
    if sets.coupling is not None:  # an IMU set: complete (its three axes load together), coupled
        src.lines.extend(coupling_lines(sets.coupling, ("r0", "r1", "r2")))
    if tracking is not None:  # the bias learned at standstills, less (canical.bus.bias_tracking)
        src.add(*tracking.inline_lines(flags))
    src.lines.extend(["    if stale:", "        stats.stale_frames += 1", "    counter = counters.tx"])
    raws = [f"s{a.at}" if a.held is None else held.get(a.held, f"values[{a.held!r}]") for a in plan.axes]
    if layout.own is not None:
        _encode_and_send_own(src, layout.own, raws, flags, "data", "own0_")
    for j, own in enumerate(layout.own_held, 1):  # the axes' other messages, from their latest frames
        src.ns[f"KEY{j}"] = own.source_key
        src.lines.extend([f"    hd{j} = held_frames.get(KEY{j})", f"    if hd{j} is not None:"])
        body: list[str] = []
        sub = _Source(body, src.ns)
        _encode_and_send_own(sub, own, raws, flags, f"hd{j}", f"own{j}_")
        src.lines.extend("    " + line for line in body)
    if layout.rate is not None:
        _encode_and_send(src, layout, layout.rate, sets, flags)
    else:  # the own-layout frame is the corrected frame
        src.lines.append("    stats.frames_out += 1")
    lines = src.lines
    source = "\n".join(with_state(lines[0], lines[1:], state, "on_raw")) + "\n"
    exec(compile(source, f"<raw frame, sets {sets.combined_id:08x}>", "exec"), src.ns)
    handler: RawHandler = src.ns["make"]()
    handler.source = source  # type: ignore[attr-defined]  # for tests and benchmarks to read
    return handler


def _decode_and_count(src: _Source, layout: FrameLayout, plan: Plan) -> None:
    """Decode the fields the code uses, count the frame, hold its inputs, check its counter."""
    width = len(layout.raw.index)
    try:  # the frame's length is the raw message's (the receive loop checked it)
        used = ({a.at for a in plan.axes} | {at for _, at in layout.raw_inputs_at} | {layout.counter_at})
        outs = [f"s{i}" if i in used else None for i in range(width)]
        src.add(*decode_lines(layout.raw_message, "data", outs))
    except NotCompilable:  # cantools decodes this frame (logged at start)
        src.lines.append(f"    {', '.join(f's{i}' for i in range(width))}, = decode(data)")
    src.lines.append("    stats.frames_in += 1")
    for name, at in layout.raw_inputs_at:
        src.lines.extend([f"    values[{name!r}] = s{at}", f"    times[{name!r}] = stamp"])
    counter_at = layout.counter_at
    if counter_at is None:
        src.lines.append("    gap = False")
    else:
        got = f"s{counter_at}"
        src.lines.extend(["    prev = counters.prev",
                          f"    gap = prev is not None and {got} != ((prev + 1) & {layout.counter_mask:#x})",
                          "    if gap:", "        stats.counter_gaps += 1",
                          f"    counters.prev = {got}"])


def _encode_and_send_own(src: _Source, own: OwnLayout, raws: list[str], flags: list[str], data: str,
                         tag: str) -> None:
    """A message again (``data``: its bytes), each axis's signal its corrected value saturated to
    the signal's range (an uncalibrated axis: its raw value, ``raws[k]``), every other bit as it
    came."""
    values: list[str] = []
    spans: list[tuple[float, float] | None] = []
    for k, (lo, hi) in zip(own.axes, own.spans, strict=True):
        if flags[k] == "True":  # uncalibrated
            values.append(raws[k])
            spans.append(None)
            continue
        zero = lo if lo > 0.0 else hi if hi < 0.0 else 0.0  # a non-finite rate is sent as 0
        r, q = f"r{k}", f"{tag}q{k}"
        src.lines.append(f"    {q} = ({lo!r} if {r} < {lo!r} else {hi!r} if {r} > {hi!r} else {r})"
                         f" if {r} - {r} == 0.0 else {zero!r}")
        values.append(q)
        spans.append((lo, hi))
    try:
        body, names, payload = encode_lines(own.message, values, [None] * len(values), tag=tag, spans=spans)
        src.add(body, names)
    except NotCompilable:  # cantools encodes this frame (logged at start)
        src.ns[f"{tag}encode"] = own.encode
        payload = f"{tag}encode(({', '.join(values)},))"
    src.ns.update({f"{tag}HEAD": own.head, "from_bytes": int.from_bytes})
    n = own.length
    frame = (f"((from_bytes({payload}, 'little') | (from_bytes({data}, 'little') & {own.keep:#x}))"
             f".to_bytes({n}, 'little'))")
    pad = f" + {own.pad!r}" if own.pad else ""
    src.lines.extend(["    try:", f"        send_own({tag}HEAD + {frame}{pad}, MSG_DONTWAIT)",
                      "    except OSError as exc:", "        send_failed(exc)"])


def _encode_and_send(src: _Source, layout: FrameLayout, rate: RateEncoder, sets: ActiveSets,
                     flags: list[str]) -> None:
    """Saturate the rates, encode the rate frame, advance its counter, send it without waiting."""
    rates = []
    for k, (lo, hi) in enumerate(rate.limits):
        r = f"r{k}"
        zero = lo if lo > 0.0 else hi if hi < 0.0 else 0.0  # a non-finite rate is sent as 0
        src.lines.append(f"    {r} = ({lo!r} if {r} < {lo!r} else {hi!r} if {r} > {hi!r} else {r})"
                         f" if {r} - {r} == 0.0 else {zero!r}")
        rates.append(r)
    # The rate frame's signals in encode_xyz's order; all but the rates are bools, the tag
    # (a constant here) and the counter (within its mask): packed as they are.
    mask = layout.tx_counter_mask
    values = [*rates, "o0", "o1", "o2", *flags, "stale", "gap", repr(sets.tag), "counter"]
    bounds = [None, None, None, *[1] * 8, sets.tag, mask]
    try:
        # The rates are saturated to their signals' ranges above: no range check needed.
        assert layout.rate_message is not None
        body, names, payload = encode_lines(layout.rate_message, values, bounds,
                                            spans=[*rate.limits, *[None] * 10])
        src.add(body, names)
    except NotCompilable:  # cantools encodes this frame (logged at start)
        payload = f"encode(({', '.join(values)}))"
    pad = f" + {layout.rate_pad!r}" if layout.rate_pad else ""
    src.lines.extend([f"    payload = {payload}", f"    counters.tx = (counter + 1) & {mask:#x}",
                      "    try:",
                      f"        send(FRAME + payload{pad}, MSG_DONTWAIT)", "    except OSError as exc:",
                      "        send_failed(exc)  # counted as dropped, or the bus is lost",
                      "    stats.frames_out += 1"])
