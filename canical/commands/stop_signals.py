"""Set a threading.Event when SIGTERM or SIGINT arrives, without a lock in the signal handler.

A Python signal handler runs in the main thread between two bytecodes, wherever that thread is.
A handler that calls ``Event.set`` takes the event's internal lock; when the signal lands while the
main thread itself holds that lock (inside ``Event.wait``, which a paced loop calls hundreds of times
a second), ``set`` waits on a lock its own thread holds, forever, and the process never stops.
Here the C-level handler writes the signal's number to a pipe (:func:`signal.set_wakeup_fd`) and a
watcher thread, which holds no lock of the main thread's, reads it and sets the event.
"""

from __future__ import annotations

import os
import signal
import threading
from collections.abc import Iterator
from contextlib import contextmanager

STOP_SIGNALS = (signal.SIGTERM, signal.SIGINT)


@contextmanager
def event_on_signals(event: threading.Event,
                     signums: tuple[signal.Signals, ...] = STOP_SIGNALS) -> Iterator[None]:
    """Within the block, any of ``signums`` sets ``event``; handlers and wakeup fd restored after.

    Must be entered from the main thread (Python's rule for signal handlers)."""
    read_fd, write_fd = os.pipe()
    os.set_blocking(write_fd, False)  # the C handler must never block on a full pipe
    wanted = {int(s) for s in signums}
    previous_fd = signal.set_wakeup_fd(write_fd, warn_on_full_buffer=False)
    previous = {s: signal.signal(s, _noted_by_wakeup_fd) for s in signums}

    def watch() -> None:
        while data := os.read(read_fd, 64):  # b"" once the write end is closed
            if wanted.intersection(data):
                event.set()

    watcher = threading.Thread(target=watch, name="stop-signals", daemon=True)
    watcher.start()
    try:
        yield
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)
        signal.set_wakeup_fd(previous_fd)
        os.close(write_fd)
        watcher.join(timeout=1.0)
        os.close(read_fd)


def _noted_by_wakeup_fd(*_: object) -> None:
    """The Python-level handler does nothing: the wakeup fd has already carried the signal."""
