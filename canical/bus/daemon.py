"""The real-time daemon: raw IMU frames in, corrected rate frames out, one frame at a time.

One thread does everything, in this order, so nothing needs a lock:

* receive one frame in the kernel's layout (the kernel's receive filters pass only the raw
  frame and the frames that carry configured inputs; error frames always come through and
  are counted): one ``recvmsg`` on the link (:mod:`.link`: canical's own raw socket on
  SocketCAN, python-can's bus behind the same calls elsewhere);
* the raw frame as expected goes straight to its handler, which decodes it, corrects its three
  axes with the sets read from ``self.sets`` **once**, encodes and sends (one function
  generated per generation of sets, :mod:`.frame_handler`, or the reference handler,
  :mod:`.reference_handler`; chosen by :mod:`.raw_path`); every other frame is counted and
  dropped or its inputs taken in (:mod:`.receive`);
* every frame out goes one way (:class:`~canical.bus.link.Sender`), never waiting;
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
import struct
import time
from collections.abc import Iterable
from typing import Any

from can import CanError
from can.interfaces.socketcan.constants import CANFD_MTU

from canical.bus import active_sets
from canical.bus.active_sets import ActiveSets, SetsNote
from canical.bus.bias_tracking import DaemonTracking
from canical.bus.daemon_config import DaemonConfig
from canical.bus.field_log import DaemonFieldLog
from canical.bus.frame_handler import frame_layout
from canical.bus.frame_state import FrameState
from canical.bus.link import LinkOpener, Sender, opener
from canical.bus.outages import Outages
from canical.bus.raw_path import RawPath
from canical.bus.receive import Classifier
from canical.bus.reloads import Reload, Reloads
from canical.bus.sd_notify import Notifier
from canical.bus.socketcan import BusLost
from canical.bus.socketcan_constants import CAN_MTU, FRAME_HEAD, STAMP_BUFFER_SIZE, TIMEVAL
from canical.bus.status import (
    STATE_DEGRADED,
    STATE_RUNNING,
    STATE_STARTING,
    STATE_STOPPING,
    Stats,
    status_frames,
    status_line,
    status_pages,
)
from canical.bus_outage import Outage
from canical.frames.codec import StatusEncoder, load_dbc

__all__ = ["Daemon"]

log = logging.getLogger("canical.serve")

MAX_WAIT_S = 0.25  # longest blocking recv, so SIGTERM/SIGHUP are acted on promptly
RELOAD_POLL_S = 0.005  # how often the loop looks whether a reload worker has finished
BURST, BURST_SPAN_S = 32, 0.02  # frames handled between two reads of the clock, at most


def _log_notes(notes: Iterable[SetsNote], why: str = "") -> None:
    """A refused set is a warning (the one in use is kept); the rest is news."""
    for note in notes:
        log.log(logging.WARNING if note.refused else logging.INFO, "%s%s", note.text,
                f" ({why})" if why else "")


class Daemon:
    """Correct the raw frames of one bus with the configured coefficient sets."""

    def __init__(self, config: DaemonConfig, *, notifier: Notifier | None = None,
                 open_link: LinkOpener | None = None, compiled: bool = True) -> None:
        """``compiled`` False keeps the reference per-frame path: cantools codecs,
        ``Corrector.correct_one`` and python-can's ``recv``/``send`` (for comparison).
        ``open_link`` opens a link (default: :func:`canical.bus.link.opener`)."""
        self.config = config
        self.notifier = notifier or Notifier()
        self.open_link = open_link or opener(config, compiled=compiled)
        db = load_dbc(config.dbc_path)
        self.layout = layout = frame_layout(config, db, compiled=compiled)
        self.raw, self.rate = layout.raw, layout.rate
        #: The status frame's encoder (None: ``frames.status: null``, no status frames sent).
        self.status = (None if config.status_message is None
                       else StatusEncoder(db.get_message_by_name(config.status_message)))
        self.stats = Stats()
        self.frames = FrameState(self.stats)
        self.sender = Sender(self.stats)
        #: The bias learned at standstills, when the configuration enables it.
        field_log = None if config.field_log is None else DaemonFieldLog(config.field_log)
        self.tracking = (None if config.bias_tracking is None
                         else DaemonTracking(config.bias_tracking, self.frames.values, field_log))
        max_age = {name: s.max_age_s for name, s in config.inputs.items()}
        self.raw_path = RawPath(layout, self, self.frames, self.sender, self.tracking, max_age,
                                compiled=compiled)
        self.classifier = Classifier(layout, self.frames)
        self.sets: ActiveSets = active_sets.build(())
        self.outages = Outages(config.interface, config.channel)
        self.reloads = Reloads(config)
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

    def open_links(self) -> None:
        """Open the sensor's bus (its kernel filters passing the raw frame and the frames that
        carry inputs), and the gateway's output bus when the own-layout frame goes to another
        channel: opened to send only (nothing on it can reach the sensor's bus)."""
        self.sender.link = self.open_link(self.config.channel, self.layout.receive_matches())
        own = self.config.own_layout
        if own is not None and own.channel is not None:
            self.sender.out = self.open_link(own.channel, None)

    def load_sets(self) -> None:
        if self.config.trust is None:  # said once, at start: whoever can write a set file can change it
            log.warning("sets are not authenticated: no trust: in %s, so any set that passes its "
                        "checks is used, whoever wrote it", self.config.path)
        sets, notes = active_sets.initial(self.config)
        _log_notes(notes)
        self.sets = sets
        for ax in sets.axes:
            if ax.raw_signal is None:
                log.info("axis %s: not configured (absent: not read, sent uncalibrated)", ax.axis)
            elif ax.corrector is None:
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
            self.sender.close()
            return 0
        self._state = STATE_RUNNING if self.sets.complete else STATE_DEGRADED
        # Logged before READY is sent: whoever waits for READY (systemd, a test) then finds the line
        # in the log already, not written a moment later among what happens next.
        log.info("ready on %s %s, sets %s", self.config.interface, self.config.channel, self.sets.describe())
        self.notifier.ready(self.status_line())
        now = time.monotonic()
        self._next_status = now
        self._next_watch = now + self.config.watch_period_s
        self._next_watchdog = now
        self._next_periodic = now
        try:
            while self._running:
                try:
                    self.serve()
                    self._periodic()
                except BusLost as exc:
                    self._reconnect(str(exc))
        finally:
            self._shutdown()
        return 0

    def serve(self, until: float | None = None) -> None:
        """Handle frames until the next periodic deadline (or ``until``): the hot path, per frame
        one ``recvmsg`` and the raw frame's handler.

        The clock is read again only after a burst: up to BURST frames spanning less than
        BURST_SPAN_S by their own timestamps (where a clock read is a system call, as in a VM,
        one per frame would cost more than the correction itself); the link's receive timeout
        is the wait for the next frame.
        """
        link = self.sender.link
        assert link is not None
        if until is not None:
            self._next_periodic = until
        recvmsg, set_wait = link.recvmsg, link.set_wait
        frame, on_raw = self.classifier.frame, self.raw_path.handler(self.sets)
        reference = self.raw_path.reference
        raw_length = self.raw.length
        raw_end = 8 + raw_length
        # A classic frame starts with can_id (flags included) and length: the raw frame's are these.
        raw_head = struct.pack("=IB", self.layout.raw_key, raw_length)
        head, stamp_of = FRAME_HEAD.unpack_from, TIMEVAL.unpack_from
        monotonic = time.monotonic
        anc_size = STAMP_BUFFER_SIZE
        while self._running:
            wait = self._next_periodic - monotonic()
            if wait <= 0.0:
                return
            set_wait(wait if wait < MAX_WAIT_S else MAX_WAIT_S)
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
                    data = cf[8:8 + length]
                    if frame(can_id, data, stamp, len(cf) == CANFD_MTU):  # a raw frame by another id
                        (on_raw if length == raw_length else reference)(data, stamp)
                if first is None:
                    first = stamp
                elif not 0.0 <= stamp - first < BURST_SPAN_S or self._next_periodic == 0.0:
                    break  # (a signal asked for the periodic step: SIGHUP, SIGTERM)

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
                self.tracking.flush()
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
        _log_notes(done.messages, done.why)
        if done.changed and self.sets is done.base:
            self.sets = done.new  # the one assignment that switches every axis at once
            if self._state in (STATE_RUNNING, STATE_DEGRADED):
                self._state = STATE_RUNNING if done.new.complete else STATE_DEGRADED

    def _send_status(self) -> None:
        """The status frame's pages (none with ``frames.status: null``)."""
        if self.status is not None:
            bias = None if self.tracking is None else self.tracking.frame_pages()
            for frame in status_frames(self.status, status_pages(self._state, self.stats, self.sets,
                                                                 self.status.pages), bias):
                self.sender.send(frame)

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
                self.open_links()
                return
            except (OSError, CanError) as exc:
                self.sender.close()
                self._bus_failed(f"cannot open: {exc}")
            if first and self._reload_requested:
                self._reload_requested = False
                self._reload(force=True, why="SIGHUP")
            self._back_off()

    def _reconnect(self, why: str) -> None:
        """The bus failed: close it, wait the outage's back-off, open it again."""
        self.sender.close()
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

    def _shutdown(self) -> None:
        self._state = STATE_STOPPING
        self.notifier.stopping(self.status_line())
        if self.sender.link is not None:
            with contextlib.suppress(BusLost):
                self._send_status()
        self.sender.close()
        if self.tracking is not None:
            self.tracking.finish()
            self.tracking.log_events()
            self.tracking.flush()
            self.tracking.save()
        log.info("stopped: %s", self.status_line())
