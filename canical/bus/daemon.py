"""The real-time daemon: raw IMU frames in, corrected rate frames out, one frame at a time.

One thread does everything, in this order, so nothing needs a lock:

* receive one frame (the kernel's receive filters pass only the raw frame and the frames
  that carry configured inputs; error frames always come through and are counted): on
  SocketCAN one ``recvmsg`` on the bus's raw socket, elsewhere python-can's ``recv``;
* classify it: error, remote, CAN FD, unknown id and wrong length are counted and dropped;
  an input frame updates the held value and time of its signals; a raw frame is decoded,
  corrected on its three axes with the sets read from ``self.sets`` **once**, encoded and sent
  (codecs generated from the DBC and correctors generated from the sets, at load:
  :mod:`canical.frames.compiler`, :mod:`canical.sets.fast_corrector`; on the raw socket all of
  it as one function generated per generation of sets, :meth:`Daemon._raw_handler`);
* between frames, at deadlines: watchdog ping, status frames and systemd STATUS, file checks
  and SIGHUP reloads. Signal handlers only set flags; the loop acts on them.

A reload builds and validates a complete new :class:`~canical.bus.active_sets.ActiveSets` on a
worker thread (so frames keep flowing meanwhile) and the loop then assigns it in one
statement, between two frames: no frame ever sees two sets.

The interface going away (down, bus-off, unplugged) shows up as an error from ``recv`` or
``send`` (binding to a down vcan succeeds, so opening alone proves nothing): the daemon closes
the bus and reopens it with a capped back-off until a status frame goes out again, and carries
on with the same sets and counters. The outage is logged when it starts, once a minute while it
lasts and when it ends, and shown in STATUS. The watchdog is pinged whatever the bus does: it
watches the daemon's loop, and a bus outage is not a reason to kill a working daemon.
"""

from __future__ import annotations

import contextlib
import errno
import logging
import signal
import socket
import struct
import threading
import time
import weakref
from collections.abc import Callable
from math import isfinite
from socket import MSG_DONTWAIT
from typing import Any

import can

from canical.bus import active_sets
from canical.bus.active_sets import ActiveSets
from canical.bus.daemon_config import DaemonConfig
from canical.bus.sd_notify import Notifier
from canical.bus_outage import OUTAGE_LOG_EVERY_S, REOPEN_BACKOFF_S, Outage
from canical.frames.codec import RateEncoder, RawDecoder, StatusEncoder, load_dbc
from canical.frames.compiler import NotCompilable, decode_lines, encode_lines
from canical.sets.corrector import Corrector
from canical.sets.fast_corrector import CorrectOne, compile_corrector, corrector_lines, why_not, with_state

log = logging.getLogger("canical.serve")

STATE_STARTING, STATE_RUNNING, STATE_DEGRADED, STATE_STOPPING = 0, 1, 2, 3
AXIS_CODES = {"x": 0, "y": 1, "z": 2}
#: Status pages whose counters stop at their maximum (fault counts: 255 means "255 or more");
#: page 0's frame counters are rolling and wrap, so receivers can take differences.
SATURATING_PAGES = frozenset({2})
#: errno values that mean "not a problem of this frame": the transmit queue is full.
TX_FULL = {errno.ENOBUFS, errno.EAGAIN}
MAX_WAIT_S = 0.25  # longest blocking recv, so SIGTERM/SIGHUP are acted on promptly
RELOAD_POLL_S = 0.005  # how often the loop looks whether a reload worker has finished
BURST, BURST_SPAN_S = 32, 0.02  # frames handled between two reads of the clock, at most
WAIT_SLICE_S = 0.05  # sleeping in back-off: how often stop requests and the watchdog are served

BusFactory = Callable[..., can.BusABC]
#: Per generation of sets: the sets, (input, maximum age) pairs, per axis (raw signal position,
#: correcting function or None, inputs it needs).
AxisPlan = tuple[int, "CorrectOne | None", tuple[str, ...]]
Plan = tuple["ActiveSets | None", tuple[tuple[str, float], ...], tuple[AxisPlan, ...]]

# SocketCAN's frame: can_id with flags in its top bits, length, data from byte 8 (<linux/can.h>).
CAN_EFF_FLAG, CAN_RTR_FLAG, CAN_ERR_FLAG = 0x80000000, 0x40000000, 0x20000000
FRAME_KEY = CAN_EFF_FLAG | 0x1FFFFFFF  # what tells frames apart: the id and whether it is extended
CAN_MTU, CANFD_MTU = 16, 72
FRAME_HEAD = struct.Struct("=IBB1xB")  # can_id, len, flags, len8_dlc
TIMEVAL = struct.Struct("@ll")


def frame_key(frame_id: int, extended: bool) -> int:
    return frame_id | (CAN_EFF_FLAG if extended else 0)


def socket_frame(frame_id: int, extended: bool, payload: bytes) -> bytes:
    """A classic frame as the kernel takes it on a raw CAN socket."""
    return FRAME_HEAD.pack(frame_key(frame_id, extended), len(payload), 0, 0) + payload.ljust(8, b"\0")


class Stats:
    """Counters for the status frame and systemd STATUS (they only ever grow)."""

    __slots__ = ("bad_length", "bus_restarts", "counter_gaps", "error_frames", "fd_frames",
                 "frames_in", "frames_out", "inputs_in", "remote_frames", "stale_frames",
                 "tx_dropped", "unknown_ids")
    # Declared for the type checker; __init__ sets each slot to 0.
    bad_length: int
    bus_restarts: int
    counter_gaps: int
    error_frames: int
    fd_frames: int
    frames_in: int
    frames_out: int
    inputs_in: int
    remote_frames: int
    stale_frames: int
    tx_dropped: int
    unknown_ids: int

    def __init__(self) -> None:
        for name in self.__slots__:
            setattr(self, name, 0)

    @property
    def bad(self) -> int:
        return self.bad_length + self.unknown_ids + self.remote_frames + self.fd_frames

    def as_dict(self) -> dict[str, int]:
        return {name: getattr(self, name) for name in self.__slots__}


class _BusLost(Exception):
    """The interface failed under us; reopen it."""


class Daemon:
    """Correct the raw frames of one bus with the configured coefficient sets."""

    def __init__(self, config: DaemonConfig, *, notifier: Notifier | None = None,
                 bus_factory: BusFactory = can.Bus, compiled: bool = True) -> None:
        """``compiled`` False keeps the reference per-frame path: cantools codecs,
        ``Corrector.correct_one`` and python-can's ``recv``/``send`` (for comparison)."""
        self.config = config
        self.notifier = notifier or Notifier()
        self.bus_factory = bus_factory
        self.compiled = compiled
        db = load_dbc(config.dbc_path)
        raw_msg = db.get_message_by_name(config.raw_message)
        self.raw = RawDecoder(raw_msg, compiled=compiled)
        self._raw_message = raw_msg
        self._rate_message = db.get_message_by_name(config.rate_message)
        self.rate = RateEncoder(self._rate_message, compiled=compiled)
        self.status = StatusEncoder(db.get_message_by_name(config.status_message))
        self.counter_signal = config.counter_signal
        # Inputs carried by the raw frame itself, and decoders for the other frames that carry some.
        self.raw_inputs: tuple[tuple[str, str], ...] = tuple(
            (s.name, s.signal) for s in config.inputs.values() if s.message == raw_msg.name
        )
        self.input_frames: dict[tuple[int, bool], tuple[RawDecoder, tuple[tuple[str, str], ...]]] = {}
        for source in config.inputs.values():
            if source.message == raw_msg.name:
                continue
            msg = db.get_message_by_name(source.message)
            key = (msg.frame_id, msg.is_extended_frame)
            decoder, pairs = self.input_frames.get(key, (RawDecoder(msg, compiled=compiled), ()))
            self.input_frames[key] = (decoder, (*pairs, (source.name, source.signal)))
        # The per-frame forms of the above: frames by SocketCAN key, signals by position.
        self._raw_key = frame_key(self.raw.frame_id, self.raw.is_extended)
        self._raw_inputs_at = tuple((name, self.raw.index[sig]) for name, sig in self.raw_inputs)
        self._counter_at = None if self.counter_signal is None else self.raw.index[self.counter_signal]
        self._input_handlers = {
            frame_key(*key): (decoder.values, decoder.length, tuple((n, decoder.index[s]) for n, s in pairs))
            for key, (decoder, pairs) in self.input_frames.items()
        }
        self._raw_values, self._raw_length = self.raw.values, self.raw.length
        self._encode_rate = self.rate.encode_in_order  # None: encode_xyz arranges the values
        self._rate_head = FRAME_HEAD.pack(frame_key(self.rate.frame_id, self.rate.is_extended),
                                          self.rate.length, 0, 0)
        self._rate_pad = bytes(max(0, 8 - self.rate.length))
        self._compiled_axes: weakref.WeakKeyDictionary[Corrector, CorrectOne | None] = (
            weakref.WeakKeyDictionary())
        self._plan: Plan = (None, (), ())
        #: The raw frame's generated handler: (sets, socket, function) of the last one built.
        self._fast: tuple[ActiveSets | None, socket.socket | None, Callable[[bytes, float], None]] = (
            None, None, self._on_raw)
        self._sock: socket.socket | None = None  # the raw socket under ``_sock_of``, when usable
        self._sock_of: can.BusABC | None = None
        self._rcv_timeout = -1.0
        self.max_age = {name: s.max_age_s for name, s in config.inputs.items()}
        self.values: dict[str, float] = {}  # latest value of each input
        self.times: dict[str, float] = {}  # and the timestamp of the frame that brought it
        self.stats = Stats()
        self.sets: ActiveSets = active_sets.build(())
        self.bus: can.BusABC | None = None
        self._prev_counter: int | None = None
        self._tx_counter = 0
        self._running = True
        self._reload_requested = False
        self._reload_worker: threading.Thread | None = None
        self._reload_done: tuple[ActiveSets, ActiveSets, list[str], str] | None = None
        self._reload_again: tuple[bool, str] | None = None
        self._reload_times = (0.0, 0.0, 0.0)  # last reload: asked at (monotonic), wall and CPU seconds
        self._next_periodic = 0.0
        self._next_status = 0.0
        self._next_watch = 0.0
        self._next_watchdog = 0.0
        self._state = STATE_STARTING
        self.outage: Outage | None = None

    # ----------------------------------------------------------------------------------
    # Set-up
    # ----------------------------------------------------------------------------------

    def can_filters(self) -> list[dict[str, Any]]:
        """Kernel receive filters: the raw frame and the frames that carry inputs, nothing else."""
        keys = [(self.raw.frame_id, self.raw.is_extended), *self.input_frames]
        return [
            {"can_id": fid, "can_mask": 0x1FFFFFFF if ext else 0x7FF, "extended": ext}
            for fid, ext in dict.fromkeys(keys)
        ]

    def _bus_kwargs(self) -> dict[str, Any]:
        kwargs = dict(self.config.bus_options)
        if self.config.interface == "socketcan":
            # See CAN FD frames (to count and drop them) instead of the kernel hiding them.
            kwargs.setdefault("fd", True)
        return kwargs

    def open_bus(self) -> can.BusABC:
        return self.bus_factory(
            interface=self.config.interface,
            channel=self.config.channel,
            can_filters=self.can_filters(),
            **self._bus_kwargs(),
        )

    def load_sets(self) -> None:
        sets, messages = active_sets.initial(self.config)
        for message in messages:
            log.warning("%s", message) if "keeping" in message else log.info("%s", message)
        self.sets = sets
        for ax in sets.axes:
            if ax.corrector is None:
                log.warning("axis %s: no coefficient set, sending it uncalibrated", ax.axis)

    def request_stop(self, *_: Any) -> None:
        self._running = False
        self._next_periodic = 0.0

    def request_reload(self, *_: Any) -> None:
        self._reload_requested = True
        self._next_periodic = 0.0

    def install_signal_handlers(self) -> None:
        signal.signal(signal.SIGTERM, self.request_stop)
        signal.signal(signal.SIGINT, self.request_stop)
        signal.signal(signal.SIGHUP, self.request_reload)

    # ----------------------------------------------------------------------------------
    # The loop
    # ----------------------------------------------------------------------------------

    def run(self) -> int:
        """Serve until SIGTERM/SIGINT; returns the exit status."""
        self.load_sets()
        self._connect(first=True)
        if not self._running:
            self._close_bus()
            return 0
        self._state = STATE_RUNNING if self.sets.complete else STATE_DEGRADED
        self.notifier.ready(self.status_line())
        log.info("ready on %s %s, sets %s", self.config.interface, self.config.channel, self.sets.describe())
        now = time.monotonic()
        self._next_status = now
        self._next_watch = now + self.config.watch_period_s
        self._next_watchdog = now
        self._next_periodic = now
        try:
            while self._running:
                try:
                    self._serve_until_deadline()
                    self._periodic()
                except _BusLost as exc:
                    self._reconnect(str(exc))
        finally:
            self._shutdown()
        return 0

    def _serve_until_deadline(self) -> None:
        """Process frames until the next periodic deadline: the hot path."""
        bus = self.bus
        assert bus is not None
        if self._raw_socket() is not None:
            self._serve_socket()
            return
        recv = bus.recv
        dispatch = self._dispatch
        monotonic = time.monotonic
        while self._running:
            wait = self._next_periodic - monotonic()
            if wait <= 0.0:
                return
            wait = wait if wait < MAX_WAIT_S else MAX_WAIT_S
            # The clock is read again only after a burst: up to BURST frames spanning less than
            # BURST_SPAN_S by their own timestamps (where a clock read is a system call, as in
            # a VM, one per frame would cost more than the correction itself).
            first = None
            for _ in range(BURST):
                try:
                    msg = recv(wait)
                except can.CanError as exc:
                    raise _BusLost(f"receive failed: {exc}") from None
                if msg is None:
                    break
                dispatch(msg)
                stamp = msg.timestamp
                if first is None:
                    first = stamp
                elif not 0.0 <= stamp - first < BURST_SPAN_S:
                    break

    def _raw_socket(self) -> socket.socket | None:
        """The bus's own SocketCAN socket, when frames can go through it directly.

        python-can spends a ``select`` and two clock reads on each receive and each send; on
        the raw socket a frame costs one ``recvmsg`` and one ``send``. Only for python-can's
        socketcan bus (blocking socket, kernel timestamps on), and not with ``compiled`` off.
        """
        bus = self.bus
        if bus is not self._sock_of:
            sock = getattr(bus, "socket", None) if self.compiled else None
            usable = (sock is not None and getattr(sock, "family", None) == socket.AF_CAN
                      and sock.gettimeout() is None)
            self._sock, self._sock_of, self._rcv_timeout = (sock if usable else None), bus, -1.0
        return self._sock

    def _serve_socket(self) -> None:
        """:meth:`_serve_until_deadline` on the raw socket: per frame, ``recvmsg`` and ``send`` only.

        The wait for the next frame is the socket's receive timeout (``SO_RCVTIMEO``), set only
        when the time to the next deadline has become shorter than it (or much longer): at most
        once per burst, not once per frame.
        """
        sock = self._sock
        assert sock is not None
        recvmsg = sock.recvmsg
        frame, on_raw = self._frame, self._raw_handler(sock)
        raw_end = 8 + self.raw.length
        # A classic frame starts with can_id (flags included) and length: the raw frame's are these.
        raw_head = struct.pack("=IB", self._raw_key, self.raw.length)
        head = FRAME_HEAD.unpack_from
        stamp_of = TIMEVAL.unpack_from
        monotonic = time.monotonic
        from can.interfaces.socketcan.socketcan import RECEIVED_ANCILLARY_BUFFER_SIZE as anc_size

        while self._running:
            wait = self._next_periodic - monotonic()
            if wait <= 0.0:
                return
            wait = wait if wait < MAX_WAIT_S else MAX_WAIT_S
            if wait < self._rcv_timeout or wait > 2.0 * self._rcv_timeout:
                usec = max(1, int(wait * 1e6))  # 0 would mean "wait for ever"
                try:
                    sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO,
                                    TIMEVAL.pack(*divmod(usec, 1_000_000)))
                except OSError as exc:
                    raise _BusLost(f"receive failed: {exc}") from None
                self._rcv_timeout = usec * 1e-6
            first = None
            for _ in range(BURST):
                try:
                    cf, anc, _, _ = recvmsg(CANFD_MTU, anc_size)
                except BlockingIOError:  # the receive timeout: nothing came
                    break
                except OSError as exc:
                    raise _BusLost(f"receive failed: {exc}") from None
                sec, nsec = stamp_of(anc[0][2])
                stamp = sec + nsec * 1e-9
                if cf[:5] == raw_head and len(cf) == CAN_MTU:
                    on_raw(cf[8:raw_end], stamp)  # the raw frame as expected: straight to work
                else:
                    can_id, length, _, _ = head(cf)
                    frame(can_id, cf[8:8 + length], stamp, len(cf) == CANFD_MTU)
                if first is None:
                    first = stamp
                elif not 0.0 <= stamp - first < BURST_SPAN_S or self._next_periodic == 0.0:
                    break  # (a signal asked for the periodic step: SIGHUP, SIGTERM)

    def _dispatch(self, msg: can.Message) -> None:
        """A python-can message into :meth:`_frame`."""
        can_id = msg.arbitration_id
        if msg.is_extended_id:
            can_id |= CAN_EFF_FLAG
        if msg.is_remote_frame:
            can_id |= CAN_RTR_FLAG
        if msg.is_error_frame:
            can_id |= CAN_ERR_FLAG
        self._frame(can_id, msg.data, msg.timestamp, msg.is_fd)

    def _frame(self, can_id: int, data: bytes | bytearray, stamp: float, fd: bool) -> None:
        """One received frame, ``can_id`` with SocketCAN's flag bits: count, drop, or act on it."""
        if can_id & CAN_ERR_FLAG:
            self.stats.error_frames += 1
            return
        key = can_id & FRAME_KEY
        if key == self._raw_key:
            handler = None
        else:
            handler = self._input_handlers.get(key)
            if handler is None:
                self.stats.unknown_ids += 1
                return
        if can_id & CAN_RTR_FLAG:
            self.stats.remote_frames += 1
            return
        if fd:
            self.stats.fd_frames += 1
            return
        if handler is None:
            self._on_raw(data, stamp)
            return
        decode, length, pairs = handler
        if len(data) != length:
            self.stats.bad_length += 1
            return
        signals = decode(data)
        values, times = self.values, self.times
        for name, at in pairs:
            values[name] = signals[at]
            times[name] = stamp
        self.stats.inputs_in += 1

    def _axes_plan(self, sets: ActiveSets) -> Plan:
        """What a frame needs of ``sets``: the inputs with their maximum age, and per axis where
        its raw signal is, the function that corrects it and the inputs it needs.

        Built once per generation of sets (the first frame after a reload), so each frame uses
        the functions of exactly the sets it read. A corrector is compiled once
        (:mod:`canical.sets.fast_corrector`) and keeps its function, and its state, across reloads
        that keep it; one with terms the compiler does not know keeps ``correct_one``.
        """
        axes = []
        for ax in sets.axes:
            corrector = ax.corrector
            correct: CorrectOne | None = None
            if corrector is not None:
                if corrector not in self._compiled_axes:
                    compiled = compile_corrector(corrector) if self.compiled else None
                    if compiled is None and self.compiled:
                        log.info("axis %s: %s; correcting with the reference path", ax.axis,
                                 why_not(corrector))
                    # None for the reference path: its bound method would hold the corrector,
                    # and the entry would outlive it (one leaked set per reload).
                    self._compiled_axes[corrector] = compiled
                correct = self._compiled_axes[corrector] or corrector.correct_one
            axes.append((self.raw.index[ax.raw_signal], correct, ax.required_inputs))
        ages = tuple((name, self.max_age[name]) for name in sets.inputs)
        self._plan = (sets, ages, tuple(axes))
        return self._plan

    def _raw_handler(self, sock: socket.socket) -> Callable[[bytes, float], None]:
        """The raw frame's handler on ``sock`` for the current sets: generated code where it can be.

        :meth:`_on_raw` walks a plan, calls a function per axis, per codec and per check; at a
        few µs per frame those calls and lookups cost as much as the work. So, per generation of
        sets (and socket), :meth:`_on_raw` is written out for exactly these sets as one function:
        the decode's fields as locals, the three axes' corrections inline
        (:func:`~canical.sets.fast_corrector.corrector_lines`, the same statements as the compiled
        correctors), the staleness checks and constants written in, one ``send``. It hands a
        frame to :meth:`_on_raw` when the sets are not its own or an input the sets need has
        not arrived yet; with an axis on the reference path, or a rate frame whose signals
        :class:`~canical.frames.codec.RateEncoder` must reorder, :meth:`_on_raw` is the handler.
        """
        sets = self.sets
        fast = self._fast
        if fast[0] is sets and fast[1] is sock:
            return fast[2]
        plan = self._plan if self._plan[0] is sets else self._axes_plan(sets)
        handler = self._generate_raw_handler(sets, plan, sock)
        self._fast = (sets, sock, handler)
        return handler

    def _generate_raw_handler(self, sets: ActiveSets, plan: Plan,
                              sock: socket.socket) -> Callable[[bytes, float], None]:
        """:meth:`_on_raw` for these sets on ``sock`` as one generated function (or itself)."""
        encode = self._encode_rate
        compiled = self._compiled_axes
        if not self.compiled or encode is None or len(sets.axes) != 3 or any(
                ax.corrector is not None and compiled.get(ax.corrector) is None for ax in sets.axes):
            return self._on_raw
        carried = {name for name, _ in self._raw_inputs_at}
        awaited = [(name, age) for name, age in plan[1] if name not in carried]
        ns: dict[str, Any] = {"self": self, "SETS": sets, "general": self._on_raw, "decode": self._raw_values,
                              "stats": self.stats, "values": self.values, "times": self.times,
                              "encode": encode, "send": sock.send, "send_failed": self._send_failed,
                              "MSG_DONTWAIT": MSG_DONTWAIT, "FRAME": self._rate_head}
        fields = ", ".join(f"s{i}" for i in range(len(self.raw.index)))
        lines = ["def on_raw(data, stamp):", "    if self.sets is not SETS:",
                 "        return general(data, stamp)"]
        if awaited:
            lines += ["    try:", *(f"        t{i} = times[{name!r}]" for i, (name, _) in enumerate(awaited)),
                      "    except KeyError:  # an input the sets need has not come yet",
                      "        return general(data, stamp)"]
        try:  # the frame's length is the raw message's (the receive loop checked it)
            used = {at for at, _, _ in plan[2]} | {at for _, at in self._raw_inputs_at} | {self._counter_at}
            body, names = decode_lines(self._raw_message, "data",
                                       [f"s{i}" if i in used else None for i in range(len(self.raw.index))])
            lines += body
            ns.update(names)
        except NotCompilable:  # cantools decodes this frame (logged at start)
            lines.append(f"    {fields}, = decode(data)")
        lines.append("    stats.frames_in += 1")
        for name, at in self._raw_inputs_at:
            lines += [f"    values[{name!r}] = s{at}", f"    times[{name!r}] = stamp"]
        if self._counter_at is None:
            lines.append("    gap = False")
        else:
            lines += ["    prev = self._prev_counter",
                      f"    gap = prev is not None and s{self._counter_at} != ((prev + 1) & 0xF)",
                      "    if gap:", "        stats.counter_gaps += 1",
                      f"    self._prev_counter = s{self._counter_at}"]
        # Each input the sets read, once: the raw frame's own from its fields, the others held.
        held = {name: f"s{at}" for name, at in self._raw_inputs_at}
        for i, (name, _) in enumerate(awaited):
            lines.append(f"    i{i} = values[{name!r}]")
            held[name] = f"i{i}"
        # The raw frame's own inputs are as old as this frame: never stale (max_age_s > 0).
        # Inputs of other frames change only when those arrive: terms of them alone are kept.
        slow, state = frozenset(f"i{i}" for i in range(len(awaited))), list[str]()
        stale = " or ".join(f"stamp - t{i} > {age!r}" for i, (_, age) in enumerate(awaited)) or "False"
        lines.append(f"    stale = {stale}")
        flags = []  # the rate frame's axes in the sets' order, as _on_raw: rK, oK, flags[K]
        for k, (ax, (at, _, _)) in enumerate(zip(sets.axes, plan[2], strict=True)):
            if ax.corrector is None:  # uncalibrated: rate 0
                lines.append(f"    r{k}, o{k} = 0.0, False")
                flags.append("True")
                continue
            body, names = corrector_lines(ax.corrector, f"s{at}", "values", f"r{k}", f"o{k}", tag=f"A{k}_",
                                          held=held, cached=slow, state=state)
            lines += body
            ns.update(names)
            flags.append("False")
        lines += ["    if stale:", "        stats.stale_frames += 1", "    counter = self._tx_counter"]
        rates = []
        for k, (lo, hi) in enumerate(self.rate.limits):
            r = f"r{k}"
            zero = lo if lo > 0.0 else hi if hi < 0.0 else 0.0  # a non-finite rate is sent as 0
            lines.append(f"    {r} = ({lo!r} if {r} < {lo!r} else {hi!r} if {r} > {hi!r} else {r})"
                         f" if {r} - {r} == 0.0 else {zero!r}")
            rates.append(r)
        # The rate frame's signals in encode_xyz's order; all but the rates are bools, the tag
        # (0-15) and the counter (0-15): packed as they are where the signal holds them.
        values = [*rates, "o0", "o1", "o2", *flags, "stale", "gap", repr(sets.tag), "counter"]
        bounds = [None, None, None, *[1] * 8, sets.tag, 0xF]
        try:
            # The rates are saturated to their signals' ranges above: no range check needed.
            body, names, payload = encode_lines(self._rate_message, values, bounds,
                                                spans=[*self.rate.limits, *[None] * 10])
            lines += body
            ns.update(names)
        except NotCompilable:  # cantools encodes this frame (logged at start)
            payload = f"encode(({', '.join(values)}))"
        lines += [f"    payload = {payload}", "    self._tx_counter = (counter + 1) & 0xF", "    try:"]
        pad = f" + {self._rate_pad!r}" if self._rate_pad else ""
        lines += [f"        send(FRAME + payload{pad}, MSG_DONTWAIT)", "    except OSError as exc:",
                  "        send_failed(exc)  # counted as dropped, or the bus is lost",
                  "    stats.frames_out += 1"]
        source = "\n".join(with_state(lines[0], lines[1:], state, "on_raw")) + "\n"
        exec(compile(source, f"<raw frame, sets {sets.combined_id:08x}>", "exec"), ns)
        handler = ns["make"]()
        handler.source = source
        return handler

    def _on_raw(self, data: bytes | bytearray, stamp: float) -> None:
        """Decode, correct three axes, encode, send: once per raw frame."""
        stats = self.stats
        if len(data) != self._raw_length:
            stats.bad_length += 1
            return
        signals = self._raw_values(data)
        stats.frames_in += 1
        values, times = self.values, self.times
        for name, at in self._raw_inputs_at:
            values[name] = signals[at]
            times[name] = stamp
        gap = False
        if self._counter_at is not None:
            counter = signals[self._counter_at]
            prev = self._prev_counter
            if prev is not None and counter != ((prev + 1) & 0xF):
                gap = True
                stats.counter_gaps += 1
            self._prev_counter = counter

        sets = self.sets  # read once: this frame uses exactly this combination
        plan = self._plan
        if plan[0] is not sets:
            plan = self._axes_plan(sets)
        stale = False
        missing: tuple[str, ...] = ()
        for name, max_age in plan[1]:
            t = times.get(name)
            if t is None:
                missing = (*missing, name)
                stale = True
            elif stamp - t > max_age:
                stale = True
        (ax, fx, nx), (ay, fy, ny), (az, fz, nz) = plan[2]
        # Per axis: corrected, or uncalibrated (rate 0) without a set or an input it needs.
        if fx is None or (missing and any(n in missing for n in nx)):
            rx, ox, ux = 0.0, False, True
        else:
            (rx, ox), ux = fx(signals[ax], values), False
        if fy is None or (missing and any(n in missing for n in ny)):
            ry, oy, uy = 0.0, False, True
        else:
            (ry, oy), uy = fy(signals[ay], values), False
        if fz is None or (missing and any(n in missing for n in nz)):
            rz, oz, uz = 0.0, False, True
        else:
            (rz, oz), uz = fz(signals[az], values), False
        if stale:
            stats.stale_frames += 1
        counter = self._tx_counter
        rx = rx if isfinite(rx) else 0.0
        ry = ry if isfinite(ry) else 0.0
        rz = rz if isfinite(rz) else 0.0
        encode = self._encode_rate
        if encode is None:
            payload = self.rate.encode_xyz(rx, ry, rz, ox, oy, oz, ux, uy, uz, stale, gap, sets.tag, counter)
        else:  # encode_xyz written out: saturated to each rate signal's range
            (lx, hx), (ly, hy), (lz, hz) = self.rate.limits
            payload = encode((lx if rx < lx else hx if rx > hx else rx,
                              ly if ry < ly else hy if ry > hy else ry,
                              lz if rz < lz else hz if rz > hz else rz,
                              ox, oy, oz, ux, uy, uz, stale, gap, sets.tag, counter))
        self._tx_counter = (counter + 1) & 0xF
        sock = self._sock if self.bus is self._sock_of else self._raw_socket()
        if sock is None:
            self._send(self.rate.frame_id, self.rate.is_extended, payload)
        else:
            try:
                sock.send(self._rate_head + payload + self._rate_pad, MSG_DONTWAIT)
            except OSError as exc:
                self._send_failed(exc)  # counted as dropped, or the bus is lost
        stats.frames_out += 1

    def _send(self, frame_id: int, extended: bool, payload: bytes) -> None:
        assert self.bus is not None
        sock = self._raw_socket()
        if sock is not None:
            self._send_frame(sock, socket_frame(frame_id, extended, payload))
            return
        try:
            self.bus.send(can.Message(arbitration_id=frame_id, is_extended_id=extended, data=payload,
                                      check=False))
        except can.CanOperationError as exc:
            if exc.error_code in TX_FULL or "buffer full" in str(exc):
                self.stats.tx_dropped += 1
                return
            raise _BusLost(f"send failed: {exc}") from None
        except can.CanError as exc:
            raise _BusLost(f"send failed: {exc}") from None

    def _send_frame(self, sock: socket.socket, frame: bytes) -> None:
        """One frame on the raw socket, never waiting: a full transmit queue drops it (counted)."""
        try:
            sock.send(frame, MSG_DONTWAIT)
        except OSError as exc:
            self._send_failed(exc)

    def _send_failed(self, exc: OSError) -> None:
        if exc.errno in TX_FULL:
            self.stats.tx_dropped += 1
            return
        raise _BusLost(f"send failed: {exc}") from None

    # ----------------------------------------------------------------------------------
    # Between frames
    # ----------------------------------------------------------------------------------

    def _periodic(self) -> None:
        now = time.monotonic()
        # First: the loop is alive, whatever the bus does next (a status send may fail).
        self._ping_watchdog(now)
        self._finish_reload()
        if self._reload_requested:
            self._reload_requested = False
            self._start_reload(force=True, why="SIGHUP")
        if now >= self._next_watch:
            if active_sets.files_changed(self.sets):
                self._start_reload(force=False, why="file changed")
            self._next_watch = now + self.config.watch_period_s
        if now >= self._next_status:
            self._next_status = max(self._next_status + self.config.status_period_s, now)
            self._send_status()  # raises _BusLost while the bus is down
            if self.outage is not None:
                self._end_outage(now)
            self.notifier.status(self.status_line())
        deadlines = [self._next_status, self._next_watch]
        if self.notifier.watchdog_s is not None:
            deadlines.append(self._next_watchdog)
        if self._reload_worker is not None:
            deadlines.append(now + RELOAD_POLL_S)
        self._next_periodic = min(deadlines) if self._running else 0.0

    def _ping_watchdog(self, now: float) -> None:
        interval = self.notifier.watchdog_s
        if interval is not None and now >= self._next_watchdog:
            self.notifier.watchdog()
            self._next_watchdog = now + interval

    def _load(self, base: ActiveSets, *, force: bool) -> tuple[ActiveSets, list[str]]:
        """New sets from ``base``: pure building and validation, never touching ``self.sets``."""
        if force and self.config.device is not None:  # SIGHUP: read the IMU's sets again (SDO)
            return active_sets.from_device(self.config, base)
        return active_sets.reload(self.config, base, force=force)

    def _reload(self, *, force: bool, why: str) -> None:
        """Reload in the calling thread (while no frames flow: at start, with the bus down)."""
        base = self.sets
        new, messages = self._load(base, force=force)
        self._adopt(base, new, messages, why)

    def _start_reload(self, *, force: bool, why: str) -> None:
        """Build new sets on a worker thread while frames keep flowing; the loop adopts them.

        Loading, validating (and reading the device over SDO) takes milliseconds to a second:
        done here in the loop, frames would pile up in the socket's buffer or be lost.
        """
        if self._reload_worker is not None:  # one at a time; run once more after it
            pending = self._reload_again
            self._reload_again = (force or bool(pending and pending[0]), why)
            return
        base = self.sets
        asked = time.monotonic()

        def work() -> None:
            cpu = time.thread_time()
            try:
                new, messages = self._load(base, force=force)
            except Exception as exc:  # a reload must never take the daemon down
                new, messages = base, [f"reload failed ({exc}); keeping the sets in use"]
            # How long building took, in wall and in this thread's CPU time: a slow reload on a
            # busy machine shows as much more wall than CPU time.
            self._reload_times = (asked, time.monotonic() - asked, time.thread_time() - cpu)
            self._reload_done = (base, new, messages, why)

        self._reload_worker = threading.Thread(target=work, name="canical-reload", daemon=True)
        self._reload_worker.start()

    def _finish_reload(self) -> None:
        worker = self._reload_worker
        if worker is None or worker.is_alive():
            return
        worker.join()
        self._reload_worker = None
        done, self._reload_done = self._reload_done, None
        if done is not None:
            asked, built_s, cpu_s = self._reload_times
            if done[1] is not done[0]:
                log.info("reload (%s): built in %.0f ms (%.0f ms CPU), adopted %.0f ms after asked for",
                         done[3], built_s * 1e3, cpu_s * 1e3, (time.monotonic() - asked) * 1e3)
            self._adopt(*done)
        again, self._reload_again = self._reload_again, None
        if again is not None:
            self._start_reload(force=again[0], why=again[1])

    def _adopt(self, base: ActiveSets, new: ActiveSets, messages: list[str], why: str) -> None:
        for message in messages:
            (log.warning if "keeping" in message else log.info)("%s (%s)", message, why)
        if new is not base and self.sets is base:
            self.sets = new  # the one assignment that switches every axis at once
            if self._state in (STATE_RUNNING, STATE_DEGRADED):
                self._state = STATE_RUNNING if new.complete else STATE_DEGRADED

    def status_pages(self) -> list[tuple[int, dict[str, int]]]:
        """The status frame's pages: counters, one page per axis set, fault counters."""
        s = self.stats
        pages = [(0, {"State": self._state, "FramesIn": s.frames_in, "FramesOut": s.frames_out,
                      "FramesBad": s.bad, "CounterGaps": s.counter_gaps, "BusErrors": s.error_frames})]
        for ax in self.sets.axes:
            pages.append((1, {"SetAxis": AXIS_CODES[ax.axis], "SetId": ax.set_id, "SetTag": self.sets.tag,
                              "SetSource": ax.source, "Reloads": ax.reloads}))
        if 2 in self.status.pages:
            pages.append((2, {"BadLength": s.bad_length, "UnknownIds": s.unknown_ids,
                              "RemoteFrames": s.remote_frames, "FdFrames": s.fd_frames,
                              "BusRestarts": s.bus_restarts, "StaleFrames": s.stale_frames,
                              "TxDropped": s.tx_dropped}))
        return pages

    def _send_status(self) -> None:
        for page, values in self.status_pages():
            payload = self.status.encode(page, values, saturate=page in SATURATING_PAGES)
            self._send(self.status.frame_id, self.status.is_extended, payload)

    def status_line(self) -> str:
        s = self.stats
        state = ("starting", "running", "degraded", "stopping")[self._state]
        if self.outage is not None:
            down = time.monotonic() - self.outage.since
            state = f"{state}, {self.config.channel} down for {down:.0f} s ({self.outage.reason})"
        return (f"{state}: {s.frames_in} frames in, {s.frames_out} out, {s.bad} bad, "
                f"{s.counter_gaps} gaps, {s.error_frames} error frames, {s.bus_restarts} bus restarts; "
                f"sets {self.sets.describe()}")

    # ----------------------------------------------------------------------------------
    # The interface coming and going
    # ----------------------------------------------------------------------------------

    def _connect(self, *, first: bool) -> None:
        """Open the bus, retrying with back-off (and pinging the watchdog) until it works or we stop."""
        while self._running:
            try:
                self.bus = self.open_bus()
                return
            except (OSError, can.CanError) as exc:
                self._bus_failed(f"cannot open: {exc}")
            if first and self._reload_requested:
                self._reload_requested = False
                self._reload(force=True, why="SIGHUP")
            self._back_off()

    def _reconnect(self, why: str) -> None:
        """The bus failed: close it, wait the outage's back-off, open it again."""
        self._close_bus()
        self._bus_failed(why)
        self._back_off()
        self._connect(first=False)
        # Probe at once: the next periodic step sends a status frame, which ends the outage.
        self._next_status = 0.0
        self._next_periodic = 0.0

    def _bus_failed(self, why: str) -> None:
        """Start an outage (logged once) or note the latest reason of the ongoing one."""
        now = time.monotonic()
        if self.outage is None:
            self.outage = Outage(now, why)
            if self._state != STATE_STARTING:  # at start the bus was never there to lose
                self.stats.bus_restarts += 1
            log.warning("%s %s lost: %s; reopening with back-off up to %.0f s", self.config.interface,
                        self.config.channel, why, REOPEN_BACKOFF_S[-1])
            self.notifier.status(self.status_line())
        else:
            self.outage.reason = why

    def _end_outage(self, now: float) -> None:
        outage, self.outage = self.outage, None
        assert outage is not None
        log.info("%s %s reopened: back after %.1f s down (%d reopen attempts)", self.config.interface,
                 self.config.channel, now - outage.since, outage.attempts)

    def _back_off(self) -> None:
        """Sleep the outage's next back-off, pinging the watchdog and keeping STATUS current."""
        outage = self.outage
        assert outage is not None
        end = time.monotonic() + outage.delay()
        while self._running:
            now = time.monotonic()
            self._ping_watchdog(now)
            if now >= self._next_status:
                self._next_status = now + self.config.status_period_s
                self.notifier.status(self.status_line())
            if now >= outage.next_log:
                outage.next_log = now + OUTAGE_LOG_EVERY_S
                log.warning("%s %s still down after %.0f s (%d reopen attempts): %s", self.config.interface,
                            self.config.channel, now - outage.since, outage.attempts, outage.reason)
            if now >= end:
                return
            time.sleep(min(WAIT_SLICE_S, end - now))

    def _close_bus(self) -> None:
        if self.bus is not None:
            try:
                self.bus.shutdown()
            except (OSError, can.CanError) as exc:
                log.debug("closing the bus: %s", exc)
            self.bus = None

    def _shutdown(self) -> None:
        self._state = STATE_STOPPING
        self.notifier.stopping(self.status_line())
        if self.bus is not None:
            with contextlib.suppress(_BusLost):
                self._send_status()
        self._close_bus()
        log.info("stopped: %s", self.status_line())
