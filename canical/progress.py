"""Progress reporting for long work, on stderr so that stdout stays parseable.

It prints only when stderr is a terminal or ``CANICAL_PROGRESS=1`` is set, and
at most a few times per second, so that logs and CI output are not flooded.
"""

from __future__ import annotations

import os
import sys
import time
from typing import TextIO


class Progress:
    """A throttled ``label: done/total (pct)`` line for one long task."""

    def __init__(self, label: str, total: int, stream: TextIO | None = None, unit: str = "") -> None:
        self.label = label
        self.unit = f" {unit}" if unit else ""
        self.total = max(int(total), 1)
        self.stream = stream if stream is not None else sys.stderr
        self.enabled = os.environ.get("CANICAL_PROGRESS") == "1" or self.stream.isatty()
        self._last = 0.0
        self._finished = False

    def update(self, done: int) -> None:
        """Report that ``done`` units of ``total`` are finished."""
        if not self.enabled or self._finished:
            return
        now = time.monotonic()
        if now - self._last < 0.25 and done < self.total:
            return
        self._last = now
        pct = 100.0 * done / self.total
        self.stream.write(f"\r{self.label}: {done}/{self.total}{self.unit} ({pct:.0f}%)")
        if done >= self.total:
            self.stream.write("\n")
            self._finished = True  # the line is ended: a later update would start a new one
        self.stream.flush()

    def step(self, message: str) -> None:
        """Report a named stage of a multi-stage task."""
        if self.enabled:
            self.stream.write(f"{self.label}: {message}\n")
            self.stream.flush()
