"""The interface going away and coming back: the outage in progress, its log lines, its back-off.

The interface going away (down, bus-off, unplugged) shows up as an error from ``recv`` or
``send`` (binding to a down vcan succeeds, so opening alone proves nothing): the daemon closes
the bus and reopens it with a capped back-off (:mod:`canical.bus_outage`) until a status frame
goes out again. The outage is logged when it starts, once a minute while it lasts and when it
ends. While it waits, the caller's ``tick`` keeps the watchdog and STATUS going: the watchdog
watches the daemon's loop, and a bus outage is not a reason to kill a working daemon.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Callable

from canical.bus_outage import OUTAGE_LOG_EVERY_S, REOPEN_BACKOFF_S, Outage

__all__ = ["WAIT_SLICE_S", "Outages"]

log = logging.getLogger("canical.serve")

WAIT_SLICE_S = 0.05  # sleeping in back-off: how often stop requests and the watchdog are served


class Outages:
    """The outage (if any) of one interface, from its first failure until it is reported over."""

    def __init__(self, interface: str, channel: str) -> None:
        self.where = f"{interface} {channel}"
        self.current: Outage | None = None

    def failed(self, why: str, now: float) -> bool:
        """Note a failure: True when it starts an outage (logged once), False when it is the
        latest reason of the ongoing one."""
        if self.current is not None:
            self.current.reason = why
            return False
        self.current = Outage(now, why)
        log.warning("%s lost: %s; reopening with back-off up to %.0f s", self.where, why,
                    REOPEN_BACKOFF_S[-1])
        return True

    def ended(self, now: float) -> None:
        outage, self.current = self.current, None
        assert outage is not None
        log.info("%s reopened: back after %.1f s down (%d reopen attempts)", self.where, now - outage.since,
                 outage.attempts)

    def wait(self, running: Callable[[], bool], tick: Callable[[float], None]) -> None:
        """Sleep the outage's next back-off in slices, calling ``tick(now)`` each slice, logging
        again if it has lasted another minute; over early when ``running()`` turns False."""
        outage = self.current
        assert outage is not None
        end = time.monotonic() + outage.delay()
        while running():
            now = time.monotonic()
            tick(now)
            if now >= outage.next_log:
                outage.next_log = now + OUTAGE_LOG_EVERY_S
                log.warning("%s still down after %.0f s (%d reopen attempts): %s", self.where,
                            now - outage.since, outage.attempts, outage.reason)
            if now >= end:
                return
            time.sleep(min(WAIT_SLICE_S, end - now))
