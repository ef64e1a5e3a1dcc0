"""The real-time daemon: raw IMU frames in, corrected rate frames out, one frame at a time.

One thread does everything, in this order, so nothing needs a lock:

* receive one frame (the kernel's receive filters pass only the raw frame and the frames
  that carry configured inputs; error frames always come through and are counted): on
  SocketCAN one ``recvmsg`` on the bus's raw socket, elsewhere python-can's ``recv``
  (:mod:`.socketcan`);
* classify it: error, remote, CAN FD, unknown id and wrong length are counted and dropped;
  an input frame updates the held value and time of its signals; a raw frame is decoded,
  corrected on its three axes with the sets read from ``self.sets`` **once**, encoded and sent
  (codecs generated from the DBC and correctors generated from the sets, at load:
  :mod:`canical.frames.compiler`, :mod:`canical.sets.fast_corrector`; on the raw socket all of
  it as one function generated per generation of sets, :mod:`.frame_handler`);
* between frames, at deadlines: watchdog ping, status frames and systemd STATUS
  (:mod:`.status`), file checks and SIGHUP reloads. Signal handlers only set flags; the loop
  acts on them.

A reload builds and validates a complete new :class:`~canical.bus.active_sets.ActiveSets` on a
worker thread (:mod:`.reloads`, so frames keep flowing meanwhile) and the loop then assigns it
in one statement, between two frames: no frame ever sees two sets.

A lost interface (:mod:`.outages`) is closed and reopened with a capped back-off until a status
frame goes out again; the daemon carries on with the same sets and counters, and pings the
watchdog whatever the bus does.
"""

from __future__ import annotations

import contextlib
import logging
import signal
import socket
import struct
import time
import weakref
from collections.abc import Callable
from math import isfinite
from socket import MSG_DONTWAIT
from typing import Any

import can
from can.interfaces.socketcan.constants import (
    CAN_EFF_FLAG,
    CAN_ERR_FLAG,
    CAN_RAW_FILTER,
    CAN_RTR_FLAG,
    CANFD_MTU,
    SOL_CAN_RAW,
)

from canical.bus import active_sets
from canical.bus.active_sets import ActiveSets
from canical.bus.bias_tracking import DaemonTracking
from canical.bus.daemon_config import DaemonConfig
from canical.bus.frame_handler import (
    NO_PLAN,
    CompiledAxes,
    OwnLayout,
    Plan,
    RawHandler,
    frame_layout,
    generate_raw_handler,
    plan_for,
)
from canical.bus.outages import Outages
from canical.bus.reloads import Reload, Reloads
from canical.bus.sd_notify import Notifier
from canical.bus.socketcan import (
    TX_FULL,
    BusLost,
    enlarge_receive_buffer,
    raw_socket_of,
    receive_filters,
    send_message,
    set_receive_timeout,
    socket_frame,
)
from canical.bus.socketcan_constants import CAN_MTU, FRAME_HEAD, FRAME_KEY, STAMP_BUFFER_SIZE, TIMEVAL
from canical.bus.status import (
    SATURATING_PAGES,
    STATE_DEGRADED,
    STATE_RUNNING,
    STATE_STARTING,
    STATE_STOPPING,
    Stats,
    status_line,
    status_pages,
)
from canical.bus_outage import Outage
from canical.frames.codec import StatusEncoder, load_dbc
from canical.sets.imu_corrector import couple

__all__ = ["BusFactory", "Daemon"]

log = logging.getLogger("canical.serve")
BIAS_PAGE = 3  # the status frame's page for the learned bias (canical.bus.bias_tracking)

MAX_WAIT_S = 0.25  # longest blocking recv, so SIGTERM/SIGHUP are acted on promptly
RELOAD_POLL_S = 0.005  # how often the loop looks whether a reload worker has finished
BURST, BURST_SPAN_S = 32, 0.02  # frames handled between two reads of the clock, at most

BusFactory = Callable[..., can.BusABC]


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
        self.layout = layout = frame_layout(config, db, compiled=compiled)
        self.raw, self.rate = layout.raw, layout.rate
        #: The status frame's encoder (None: ``frames.status: null``, no status frames sent).
        self.status = (None if config.status_message is None
                       else StatusEncoder(db.get_message_by_name(config.status_message)))
        # The per-frame forms of the layout, read by the reference handler on every frame.
        self._raw_key, self._raw_inputs_at = layout.raw_key, layout.raw_inputs_at
        self._counter_at = layout.counter_at
        self._input_handlers = layout.input_handlers
        #: J1939 groups matched beyond their exact id: the raw frame's first, then the inputs'.
        raw_match = layout.raw_match
        self._groups = tuple(([] if raw_match is None or raw_match.exact else [(raw_match, layout.raw_key)])
                             + list(layout.masked_inputs))
        self._raw_values, self._raw_length = self.raw.values, self.raw.length
        # None: encode_xyz arranges the values (or no rate frame is sent: frames.rate null).
        self._encode_rate = None if self.rate is None else self.rate.encode_in_order
        self._rate_head, self._rate_pad = layout.rate_head, layout.rate_pad
        self._own = layout.own  # the corrected frame in the raw frame's layout (None: not sent)
        #: The latest bytes of each other message an axis comes in, when the own layout re-encodes it.
        self.held_frames: dict[int, bytes] = {}
        self._keep_frames = frozenset(o.source_key for o in layout.own_held)
        self.out_bus: can.BusABC | None = None  # the gateway's output bus (None: the sensor's bus)
        self._counter_mask, self._tx_counter_mask = layout.counter_mask, layout.tx_counter_mask
        self._compiled_axes: CompiledAxes = weakref.WeakKeyDictionary()
        self._plan: Plan = NO_PLAN
        #: The raw frame's generated handler: (sets, socket, function) of the last one built.
        self._fast: tuple[ActiveSets | None, socket.socket | None, RawHandler] = (None, None, self._on_raw)
        self._sock: socket.socket | None = None  # the raw socket under ``_sock_of``, when usable
        self._sock_of: can.BusABC | None = None
        self._rcv_timeout = -1.0
        self.max_age = {name: s.max_age_s for name, s in config.inputs.items()}
        self.values: dict[str, float] = {}  # latest value of each input
        self.times: dict[str, float] = {}  # and the timestamp of the frame that brought it
        self.stats = Stats()
        #: The bias learned at standstills, when the configuration enables it.
        self.tracking = (None if config.bias_tracking is None
                         else DaemonTracking(config.bias_tracking, self.values))
        self.sets: ActiveSets = active_sets.build(())
        self.bus: can.BusABC | None = None
        self.outages = Outages(config.interface, config.channel)
        self.reloads = Reloads(config)
        self._prev_counter: int | None = None
        self._tx_counter = 0
        self._running = True
        self._reload_requested = False
        self._next_periodic = 0.0
        self._next_status = 0.0
        self._next_watch = 0.0
        self._next_watchdog = 0.0
        self._state = STATE_STARTING

    @property
    def outage(self) -> Outage | None:
        """The bus outage in progress, if any."""
        return self.outages.current

    # ----------------------------------------------------------------------------------
    # Set-up
    # ----------------------------------------------------------------------------------

    def can_filters(self) -> list[dict[str, Any]]:
        """Kernel receive filters: the raw frame and the frames that carry inputs, nothing else."""
        return receive_filters(self.layout.receive_matches())

    def open_bus(self) -> can.BusABC:
        kwargs = dict(self.config.bus_options)
        if self.config.interface == "socketcan":
            # See CAN FD frames (to count and drop them) instead of the kernel hiding them.
            kwargs.setdefault("fd", True)
        bus = self.bus_factory(interface=self.config.interface, channel=self.config.channel,
                               can_filters=self.can_filters(), **kwargs)
        enlarge_receive_buffer(bus)  # a moment's stall of the host loses no frame
        return bus

    def open_output_bus(self) -> can.BusABC | None:
        """The gateway's output bus, when the own-layout frame goes to another channel: opened to
        send only. Nothing is read from it (its kernel filter passes no frame), so nothing on it
        can reach the sensor's bus."""
        own = self.config.own_layout
        if own is None or own.channel is None:
            return None
        bus = self.bus_factory(interface=self.config.interface, channel=own.channel,
                               **dict(self.config.bus_options))
        sock = raw_socket_of(bus)
        if sock is not None:
            sock.setsockopt(SOL_CAN_RAW, CAN_RAW_FILTER, b"")  # no filter: no frame is received
        return bus

    def load_sets(self) -> None:
        sets, messages = active_sets.initial(self.config)
        for note in messages:
            log.log(logging.WARNING if note.refused else logging.INFO, "%s", note.text)
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
                except BusLost as exc:
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
                    raise BusLost(f"receive failed: {exc}") from None
                if msg is None:
                    break
                dispatch(msg)
                stamp = msg.timestamp
                if first is None:
                    first = stamp
                elif not 0.0 <= stamp - first < BURST_SPAN_S:
                    break

    def _raw_socket(self) -> socket.socket | None:
        """The bus's own SocketCAN socket, when frames can go through it directly (not with
        ``compiled`` off); looked up once per bus."""
        bus = self.bus
        if bus is not self._sock_of:
            self._sock = raw_socket_of(bus) if self.compiled else None
            self._sock_of, self._rcv_timeout = bus, -1.0
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
        anc_size = STAMP_BUFFER_SIZE

        while self._running:
            wait = self._next_periodic - monotonic()
            if wait <= 0.0:
                return
            wait = wait if wait < MAX_WAIT_S else MAX_WAIT_S
            if wait < self._rcv_timeout or wait > 2.0 * self._rcv_timeout:
                self._rcv_timeout = set_receive_timeout(sock, wait)
            first = None
            for _ in range(BURST):
                try:
                    cf, anc, _, _ = recvmsg(CANFD_MTU, anc_size)
                except BlockingIOError:  # the receive timeout: nothing came
                    break
                except OSError as exc:
                    raise BusLost(f"receive failed: {exc}") from None
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
        """A python-can message into :meth:`_frame`, its id with the flags the raw socket would set."""
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
                known = self._group_key(key)
                if known is None:
                    self.stats.unknown_ids += 1
                    return
                handler = None if known == self._raw_key else self._input_handlers[known]
                key = known
        if can_id & CAN_RTR_FLAG:
            self.stats.remote_frames += 1
            return
        if fd:
            self.stats.fd_frames += 1
            return
        if handler is None:
            # The generated handler (it hands over to the reference one when not its sets').
            if len(data) == self._raw_length and self._fast[1] is self._sock:
                self._fast[2](bytes(data), stamp)
            else:
                self._on_raw(data, stamp)
            return
        if len(data) != handler.length:
            self.stats.bad_length += 1
            return
        signals = handler.decode(data)
        if key in self._keep_frames:
            self.held_frames[key] = bytes(data)
        values, times = self.values, self.times
        for name, at in handler.inputs_at:
            values[name] = signals[at]
            times[name] = stamp
        self.stats.inputs_in += 1

    def _group_key(self, key: int) -> int | None:
        """The key of the message a frame whose id is not a message's own belongs to: a J1939
        group at another priority, destination or source (None: none of the daemon's)."""
        if not key & CAN_EFF_FLAG or not self._groups:
            return None
        can_id = key & ~CAN_EFF_FLAG
        for match, known in self._groups:
            if match.matches(can_id, True):
                return known
        return None

    def _axes_plan(self, sets: ActiveSets) -> Plan:
        """What a frame needs of ``sets`` (:func:`~canical.bus.frame_handler.plan_for`), kept
        until the sets change."""
        self._plan = plan_for(sets, self.layout, self.max_age, self._compiled_axes, compiled=self.compiled)
        if self.tracking is not None:
            self.tracking.for_sets(sets.combined_id, tuple(ax.axis for ax in sets.axes),
                                   tuple(None if ax.corrector is None else ax.corrector.cset.fit
                                         for ax in sets.axes),
                                   joint=sets.coupling is not None and sets.complete)
        return self._plan

    def _raw_handler(self, sock: socket.socket) -> RawHandler:
        """The raw frame's handler on ``sock`` for the current sets: generated code
        (:func:`~canical.bus.frame_handler.generate_raw_handler`) where it can be, else
        :meth:`_on_raw` (an axis on the reference path, or a rate frame whose signals
        :class:`~canical.frames.codec.RateEncoder` must reorder). Built once per generation of
        sets and socket."""
        sets = self.sets
        fast = self._fast
        if fast[0] is sets and fast[1] is sock:
            return fast[2]
        plan = self._plan if self._plan.sets is sets else self._axes_plan(sets)
        handler: RawHandler = self._on_raw
        compiled = self._compiled_axes
        encode = self._encode_rate
        send_own = self._own_send(sock)
        in_order = encode is not None or self.rate is None  # the rate frame's signals as generated code sends
        if self.compiled and in_order and send_own is not None and len(sets.axes) == 3 and all(
                ax.corrector is None or compiled.get(ax.corrector) is not None for ax in sets.axes):
            names = {"stats": self.stats, "values": self.values, "times": self.times, "encode": encode,
                     "send": sock.send, "send_own": send_own, "send_failed": self._send_failed,
                     "held_frames": self.held_frames}
            handler = generate_raw_handler(self.layout, sets, plan, owner=self, general=self._on_raw,
                                           names=names, tracking=self.tracking)
        self._fast = (sets, sock, handler)
        return handler

    def _own_send(self, sock: socket.socket) -> Callable[..., int] | None:
        """The own-layout frame's ``send`` for generated code: the sensor socket's, or the
        gateway's output socket's (None: the output bus has none, the reference path sends)."""
        if self._own is None or not self._own.gateway:
            return sock.send
        out = raw_socket_of(self.out_bus) if self.out_bus is not None else None
        return None if out is None else out.send

    def _send_own_layout(self, data: bytes | bytearray, raws: tuple[Any, Any, Any],
                         rates: tuple[float | None, float | None, float | None]) -> None:
        """The reference path's own-layout frames: the raw frame (and each other message an axis
        comes in, from its latest frame), each calibrated axis's signal its corrected rate
        (``rates[k]``, None: uncalibrated, its raw value ``raws[k]``) saturated to its range, the
        rest as it came."""
        assert self._own is not None
        for own in (self._own, *self.layout.own_held):
            source = data if own.source_key is None else self.held_frames.get(own.source_key)
            if source is None:  # that message has not come yet
                continue
            values = []
            for k, (lo, hi) in zip(own.axes, own.spans, strict=True):
                rate = rates[k]
                values.append(raws[k] if rate is None else lo if rate < lo else hi if rate > hi else rate)
            self._send_own(own, own.payload(source, values))

    def _send_own(self, own: OwnLayout, payload: bytes) -> None:
        bus = self.out_bus if own.gateway else self.bus
        sock = raw_socket_of(bus) if self.compiled else None
        if sock is not None:
            try:
                sock.send(own.head + payload + own.pad, MSG_DONTWAIT)
            except OSError as exc:
                self._send_failed(exc)
        elif bus is not None and not send_message(bus, own.frame_id, own.extended, payload):
            self.stats.tx_dropped += 1

    def _on_raw(self, data: bytes | bytearray, stamp: float) -> None:
        """Decode, correct three axes (and couple them, from an IMU set), encode, send: once per raw
        frame (the reference handler)."""
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
            if prev is not None and counter != ((prev + 1) & self._counter_mask):
                gap = True
                stats.counter_gaps += 1
            self._prev_counter = counter

        sets = self.sets  # read once: this frame uses exactly this combination
        plan = self._plan
        if plan.sets is not sets:
            plan = self._axes_plan(sets)
        stale = False
        missing: tuple[str, ...] = ()
        for name, max_age in plan.ages:
            t = times.get(name)
            if t is None:
                missing = (*missing, name)
                stale = True
            elif stamp - t > max_age:
                stale = True
        px, py, pz = plan.axes
        # Per axis: corrected, or uncalibrated (rate 0) without a set or an input it needs.
        fx, fy, fz = px.correct, py.correct, pz.correct
        if fx is None or (missing and any(n in missing for n in px.needs)):
            rx, ox, ux = 0.0, False, True
        else:
            (rx, ox), ux = fx(signals[px.at] if px.held is None else values[px.held], values), False
        if fy is None or (missing and any(n in missing for n in py.needs)):
            ry, oy, uy = 0.0, False, True
        else:
            (ry, oy), uy = fy(signals[py.at] if py.held is None else values[py.held], values), False
        if fz is None or (missing and any(n in missing for n in pz.needs)):
            rz, oz, uz = 0.0, False, True
        else:
            (rz, oz), uz = fz(signals[pz.at] if pz.held is None else values[pz.held], values), False
        if sets.coupling is not None:  # an IMU set: its axes' rates are coupled, all three or none
            if ux or uy or uz:
                rx, ry, rz, ux, uy, uz = 0.0, 0.0, 0.0, True, True, True
            else:
                rx, ry, rz = couple(sets.coupling, rx, ry, rz)
        if self.tracking is not None:
            rx, ry, rz = self.tracking(stamp, rx, ry, rz, ux, uy, uz)
        if stale:
            stats.stale_frames += 1
        counter = self._tx_counter
        rx = rx if isfinite(rx) else 0.0
        ry = ry if isfinite(ry) else 0.0
        rz = rz if isfinite(rz) else 0.0
        if self._own is not None:
            raws = (signals[px.at] if px.held is None else values.get(px.held),
                    signals[py.at] if py.held is None else values.get(py.held),
                    signals[pz.at] if pz.held is None else values.get(pz.held))
            self._send_own_layout(data, raws, (None if ux else rx, None if uy else ry, None if uz else rz))
        rate = self.rate
        if rate is None:  # frames.rate null: the own-layout frame is the corrected frame
            stats.frames_out += 1
            return
        encode = self._encode_rate
        if encode is None:
            payload = rate.encode_xyz(rx, ry, rz, ox, oy, oz, ux, uy, uz, stale, gap, sets.tag, counter)
        else:  # encode_xyz written out: saturated to each rate signal's range
            (lx, hx), (ly, hy), (lz, hz) = rate.limits
            payload = encode((lx if rx < lx else hx if rx > hx else rx,
                              ly if ry < ly else hy if ry > hy else ry,
                              lz if rz < lz else hz if rz > hz else rz,
                              ox, oy, oz, ux, uy, uz, stale, gap, sets.tag, counter))
        self._tx_counter = (counter + 1) & self._tx_counter_mask
        sock = self._sock if self.bus is self._sock_of else self._raw_socket()
        if sock is None:
            self._send(rate.frame_id, rate.is_extended, payload)
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
            try:  # never waiting: a full transmit queue drops the frame (counted)
                sock.send(socket_frame(frame_id, extended, payload), MSG_DONTWAIT)
            except OSError as exc:
                self._send_failed(exc)
        elif not send_message(self.bus, frame_id, extended, payload):
            self.stats.tx_dropped += 1

    def _send_failed(self, exc: OSError) -> None:
        if exc.errno in TX_FULL:
            self.stats.tx_dropped += 1
            return
        raise BusLost(f"send failed: {exc}") from None

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
            self.reloads.start(self.sets, force=True, why="SIGHUP")
        if now >= self._next_watch:
            if active_sets.files_changed(self.sets):
                self.reloads.start(self.sets, force=False, why="file changed")
            self._next_watch = now + self.config.watch_period_s
        if now >= self._next_status:
            self._next_status = max(self._next_status + self.config.status_period_s, now)
            self._send_status()  # raises BusLost while the bus is down
            if self.outages.current is not None:
                self.outages.ended(now)
            if self.tracking is not None:
                self.tracking.log_events()
                self.tracking.save()
            self.notifier.status(self.status_line())
        deadlines = [self._next_status, self._next_watch]
        if self.notifier.watchdog_s is not None:
            deadlines.append(self._next_watchdog)
        if self.reloads.busy:
            deadlines.append(now + RELOAD_POLL_S)
        self._next_periodic = min(deadlines) if self._running else 0.0

    def _ping_watchdog(self, now: float) -> None:
        interval = self.notifier.watchdog_s
        if interval is not None and now >= self._next_watchdog:
            self.notifier.watchdog()
            self._next_watchdog = now + interval

    def _reload(self, *, force: bool, why: str) -> None:
        """Reload in the calling thread (while no frames flow: at start, with the bus down)."""
        self._adopt(self.reloads.now(self.sets, force=force, why=why))

    def _finish_reload(self) -> None:
        """Adopt what the reload worker built, once it has finished; start the one queued behind it."""
        done = self.reloads.finished()
        if done is None:
            return
        if done.changed:
            log.info("reload (%s): built in %.0f ms (%.0f ms CPU), adopted %.0f ms after asked for",
                     done.why, done.built_s * 1e3, done.cpu_s * 1e3, (time.monotonic() - done.asked) * 1e3)
        self._adopt(done)
        self.reloads.start_queued(self.sets)

    def _adopt(self, done: Reload) -> None:
        for note in done.messages:
            log.log(logging.WARNING if note.refused else logging.INFO, "%s (%s)", note.text, done.why)
        if done.changed and self.sets is done.base:
            self.sets = done.new  # the one assignment that switches every axis at once
            if self._state in (STATE_RUNNING, STATE_DEGRADED):
                self._state = STATE_RUNNING if done.new.complete else STATE_DEGRADED

    def status_pages(self) -> list[tuple[int, dict[str, int]]]:
        """The status frame's pages: counters, one page per axis set, fault counters."""
        pages = (0, 1, 2) if self.status is None else self.status.pages
        return status_pages(self._state, self.stats, self.sets, pages)

    def _send_status(self) -> None:
        if self.status is None:  # frames.status: null
            return
        for page, values in self.status_pages():
            payload = self.status.encode(page, values, saturate=page in SATURATING_PAGES)
            self._send(self.status.frame_id, self.status.is_extended, payload)
        if self.tracking is not None and BIAS_PAGE in self.status.pages:
            for bias in self.tracking.frame_pages():
                payload = self.status.encode_physical(BIAS_PAGE, bias)
                self._send(self.status.frame_id, self.status.is_extended, payload)

    def status_line(self) -> str:
        line = status_line(self._state, self.stats, self.sets, channel=self.config.channel,
                           outage=self.outages.current, now=time.monotonic())
        tracked = "" if self.tracking is None else self.tracking.status_text()
        return f"{line}; {tracked}" if tracked else line

    # ----------------------------------------------------------------------------------
    # The interface coming and going
    # ----------------------------------------------------------------------------------

    def _connect(self, *, first: bool) -> None:
        """Open the bus, retrying with back-off (and pinging the watchdog) until it works or we stop."""
        while self._running:
            try:
                self.bus = self.open_bus()
                self.out_bus = self.open_output_bus()
                return
            except (OSError, can.CanError) as exc:
                self._close_bus()
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
        """Start an outage (logged once, a restart once the bus had been up) or note its latest reason."""
        if self.outages.failed(why, time.monotonic()):
            if self._state != STATE_STARTING:  # at start the bus was never there to lose
                self.stats.bus_restarts += 1
            self.notifier.status(self.status_line())

    def _back_off(self) -> None:
        """Sleep the outage's next back-off, pinging the watchdog and keeping STATUS current."""

        def tick(now: float) -> None:
            self._ping_watchdog(now)
            if now >= self._next_status:
                self._next_status = now + self.config.status_period_s
                self.notifier.status(self.status_line())

        self.outages.wait(lambda: self._running, tick)

    def _close_bus(self) -> None:
        if self.out_bus is not None:
            try:
                self.out_bus.shutdown()
            except (OSError, can.CanError) as exc:
                log.debug("closing the output bus: %s", exc)
            self.out_bus = None
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
            with contextlib.suppress(BusLost):
                self._send_status()
        self._close_bus()
        if self.tracking is not None:
            self.tracking.log_events()
            self.tracking.save()
        log.info("stopped: %s", self.status_line())
