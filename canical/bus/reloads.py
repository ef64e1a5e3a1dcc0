"""Reloading the sets while frames keep flowing: built on a worker thread, adopted by the loop.

Loading, validating (and reading the device over SDO) takes milliseconds to a second: done in
the loop, frames would pile up in the socket's buffer or be lost. So a reload runs on a worker
thread, one at a time (a request meanwhile runs once more after it), and hands back a
:class:`Reload`: the sets it started from and the sets it built. The loop adopts the new sets
in one assignment between two frames, and only if they still replace what is in use.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass

from canical.bus import active_sets
from canical.bus.active_sets import ActiveSets, SetsNote
from canical.bus.daemon_config import DaemonConfig

__all__ = ["Reload", "Reloads", "build_sets"]


@dataclass(frozen=True)
class Reload:
    """A finished reload: ``new`` is ``base`` itself when nothing changed."""

    base: ActiveSets  # the sets in use when it started
    new: ActiveSets
    messages: tuple[SetsNote, ...]  # what happened, to log
    why: str  # "SIGHUP", "file changed", ...
    asked: float = 0.0  # when it was asked for (monotonic)
    built_s: float = 0.0  # how long building took, wall
    cpu_s: float = 0.0  # and in the worker's CPU time (much less than wall: a busy machine)

    @property
    def changed(self) -> bool:
        return self.new is not self.base


def build_sets(config: DaemonConfig, base: ActiveSets, *, force: bool) -> tuple[ActiveSets, list[SetsNote]]:
    """New sets from ``base``: pure building and validation, never touching the sets in use.

    ``force`` (SIGHUP) reads every file again, and the device's sets when it is configured;
    otherwise only the files that changed are read.
    """
    if force and config.device is not None:  # SIGHUP: read the IMU's sets again (SDO)
        return active_sets.from_device(config, base)
    return active_sets.reload(config, base, force=force)


@dataclass(frozen=True)
class _Queued:
    force: bool
    why: str


class Reloads:
    """The reload worker: at most one at a time, and at most one more queued behind it."""

    def __init__(self, config: DaemonConfig) -> None:
        self.config = config
        self._worker: threading.Thread | None = None
        self._done: Reload | None = None
        self._queued: _Queued | None = None

    @property
    def busy(self) -> bool:
        return self._worker is not None

    def now(self, base: ActiveSets, *, force: bool, why: str) -> Reload:
        """Reload in the calling thread (while no frames flow: at start, with the bus down)."""
        new, messages = build_sets(self.config, base, force=force)
        return Reload(base, new, tuple(messages), why)

    def start(self, base: ActiveSets, *, force: bool, why: str) -> None:
        """Build new sets from ``base`` on a worker thread; while one works, queue one more run
        (forced if any request was)."""
        if self._worker is not None:
            queued = self._queued
            self._queued = _Queued(force or bool(queued and queued.force), why)
            return
        asked = time.monotonic()

        def work() -> None:
            cpu = time.thread_time()
            try:
                new, messages = build_sets(self.config, base, force=force)
            except Exception as exc:  # a reload must never take the daemon down
                failed = SetsNote(f"reload failed ({exc}); keeping the sets in use", refused=True)
                new, messages = base, [failed]
            # How long building took, in wall and in this thread's CPU time: a slow reload on a
            # busy machine shows as much more wall than CPU time.
            self._done = Reload(base, new, tuple(messages), why, asked, time.monotonic() - asked,
                                time.thread_time() - cpu)

        self._worker = threading.Thread(target=work, name="canical-reload", daemon=True)
        self._worker.start()

    def finished(self) -> Reload | None:
        """The worker's result once it has finished (handed over once); None before."""
        worker = self._worker
        if worker is None or worker.is_alive():
            return None
        worker.join()
        self._worker = None
        done, self._done = self._done, None
        return done

    def start_queued(self, base: ActiveSets) -> None:
        """Run the request that came while the last worker worked, if one did, from ``base``."""
        queued, self._queued = self._queued, None
        if queued is not None:
            self.start(base, force=queued.force, why=queued.why)
