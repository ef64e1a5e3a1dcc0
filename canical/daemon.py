"""The real-time daemon: raw IMU frames in, corrected rate frames out, one frame at a time.

One thread does everything, in this order, so nothing needs a lock:

* ``recv`` one frame (the kernel's receive filters pass only the raw frame and the frames
  that carry configured inputs; error frames always come through and are counted);
* classify it: error, remote, CAN FD, unknown id and wrong length are counted and dropped;
  an input frame updates the held value and time of its signals; a raw frame is decoded,
  corrected on its three axes with the sets read from ``self.sets`` **once**, encoded and sent;
* between frames, at deadlines: watchdog ping, status frames and systemd STATUS, file checks
  and SIGHUP reloads. Signal handlers only set flags; the loop acts on them.

A reload builds and validates a complete new :class:`~canical.active_sets.ActiveSets` on a
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
import math
import signal
import threading
import time
from collections.abc import Callable
from typing import Any

import can

from canical import active_sets
from canical.active_sets import ActiveSets
from canical.daemon_config import DaemonConfig
from canical.frame_codec import RateEncoder, RawDecoder, StatusEncoder, load_dbc
from canical.sd_notify import Notifier

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
#: Pause before each reopen while the bus stays down: doubling from 50 ms, capped at 2 s.
REOPEN_BACKOFF_S = (0.05, 0.1, 0.2, 0.4, 0.8, 1.6, 2.0)
OUTAGE_LOG_EVERY_S = 60.0  # a lasting outage is logged again this often, not on every attempt
WAIT_SLICE_S = 0.05  # sleeping in back-off: how often stop requests and the watchdog are served

BusFactory = Callable[..., can.BusABC]


class Stats:
    """Counters for the status frame and systemd STATUS (they only ever grow)."""

    __slots__ = ("bad_length", "bus_restarts", "counter_gaps", "error_frames", "fd_frames",
                 "frames_in", "frames_out", "inputs_in", "remote_frames", "stale_frames",
                 "tx_dropped", "unknown_ids")

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


class Outage:
    """One bus outage: from the first failure until a status frame goes out again."""

    __slots__ = ("attempts", "next_log", "reason", "since")

    def __init__(self, since: float, reason: str) -> None:
        self.since = since
        self.reason = reason  # the latest failure
        self.attempts = 0  # reopen attempts so far
        self.next_log = since + OUTAGE_LOG_EVERY_S

    def delay(self) -> float:
        """Back-off before the next reopen attempt (and count the attempt)."""
        delay = REOPEN_BACKOFF_S[min(self.attempts, len(REOPEN_BACKOFF_S) - 1)]
        self.attempts += 1
        return delay


class Daemon:
    """Correct the raw frames of one bus with the configured coefficient sets."""

    def __init__(self, config: DaemonConfig, *, notifier: Notifier | None = None,
                 bus_factory: BusFactory = can.Bus) -> None:
        self.config = config
        self.notifier = notifier or Notifier()
        self.bus_factory = bus_factory
        db = load_dbc(config.dbc_path)
        raw_msg = db.get_message_by_name(config.raw_message)
        self.raw = RawDecoder(raw_msg)
        self.rate = RateEncoder(db.get_message_by_name(config.rate_message))
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
            decoder, pairs = self.input_frames.get(key, (RawDecoder(msg), ()))
            self.input_frames[key] = (decoder, (*pairs, (source.name, source.signal)))
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

    def _dispatch(self, msg: can.Message) -> None:
        stats = self.stats
        if msg.is_error_frame:
            stats.error_frames += 1
            return
        key = (msg.arbitration_id, msg.is_extended_id)
        if key == (self.raw.frame_id, self.raw.is_extended):
            handler: tuple[RawDecoder, Any] | None = None
        else:
            handler = self.input_frames.get(key)
            if handler is None:
                stats.unknown_ids += 1
                return
        if msg.is_remote_frame:
            stats.remote_frames += 1
            return
        if msg.is_fd:
            stats.fd_frames += 1
            return
        if handler is None:
            self._on_raw(msg)
            return
        decoder, pairs = handler
        data = msg.data
        if len(data) != decoder.length:
            stats.bad_length += 1
            return
        signals = decoder.decode(data)
        stamp = msg.timestamp
        values, times = self.values, self.times
        for name, sig in pairs:
            values[name] = signals[sig]
            times[name] = stamp
        stats.inputs_in += 1

    def _on_raw(self, msg: can.Message) -> None:
        """Decode, correct three axes, encode, send: once per raw frame."""
        stats = self.stats
        data = msg.data
        if len(data) != self.raw.length:
            stats.bad_length += 1
            return
        signals = self.raw.decode(data)
        stats.frames_in += 1
        stamp = msg.timestamp
        values, times = self.values, self.times
        for name, sig in self.raw_inputs:
            values[name] = signals[sig]
            times[name] = stamp
        gap = False
        if self.counter_signal is not None:
            counter = signals[self.counter_signal]
            prev = self._prev_counter
            if prev is not None and counter != ((prev + 1) & 0xF):
                gap = True
                stats.counter_gaps += 1
            self._prev_counter = counter

        sets = self.sets  # read once: this frame uses exactly this combination
        stale = False
        missing: tuple[str, ...] = ()
        for name in sets.inputs:
            t = times.get(name)
            if t is None:
                missing = (*missing, name)
                stale = True
            elif stamp - t > self.max_age[name]:
                stale = True
        rates = [0.0, 0.0, 0.0]
        oos = [False, False, False]
        uncal = [True, True, True]
        for i, ax in enumerate(sets.axes):
            corrector = ax.corrector
            if corrector is None or (missing and any(n in missing for n in ax.required_inputs)):
                continue
            rate, out = corrector.correct_one(signals[ax.raw_signal], values)
            rates[i] = rate if math.isfinite(rate) else 0.0
            oos[i] = out
            uncal[i] = False
        if stale:
            stats.stale_frames += 1
        payload = self.rate.encode(rates, oos, uncal, stale, gap, sets.tag, self._tx_counter)
        self._tx_counter = (self._tx_counter + 1) & 0xF
        self._send(self.rate.frame_id, self.rate.is_extended, payload)
        stats.frames_out += 1

    def _send(self, frame_id: int, extended: bool, payload: bytes) -> None:
        assert self.bus is not None
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

        def work() -> None:
            try:
                new, messages = self._load(base, force=force)
            except Exception as exc:  # a reload must never take the daemon down
                new, messages = base, [f"reload failed ({exc}); keeping the sets in use"]
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
