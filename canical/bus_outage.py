"""A lost CAN bus: how long to wait before each reopen, and how often to say it is still down.

The daemon and the emulated IMU both ride out an interface that goes away (a vcan set down, a
USB adapter unplugged): one log line when the outage starts, one a minute while it lasts, one
when it ends, and reopen attempts backing off from 50 ms to 2 s, so a long outage costs
neither the journal nor the CPU. The policy lives here, once, for both.
"""

from __future__ import annotations

#: Pause before each reopen while the bus stays down: doubling from 50 ms, capped at 2 s.
REOPEN_BACKOFF_S = (0.05, 0.1, 0.2, 0.4, 0.8, 1.6, 2.0)
OUTAGE_LOG_EVERY_S = 60.0  # a lasting outage is logged again this often, not on every attempt


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
