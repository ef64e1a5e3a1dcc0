"""An operator offering sets to a running daemon with SIGHUP, from a thread, while frames stream.

Why shared: the reload stress test and the trust test both run ``Daemon.run`` (receive loop,
reload worker, the real SIGHUP handler) in the test's own thread, while another thread waits
for a frame count, writes set files, sends SIGHUP to the process and waits for the reload to
be done. The two wrote that thread, the handlers' save and restore and the failure reporting
out each on their own.
"""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass

from canical.bus.daemon import Daemon

RELOAD_TIMEOUT_S = 20.0


@dataclass(frozen=True)
class Offer:
    """One step: once ``after_frames`` raw frames are in, ``write`` the files, SIGHUP ``hups``
    times (a second while the first reload is still being built), wait until ``done``."""

    after_frames: int
    write: Callable[[], None]
    done: Callable[[], bool]
    what: str  # named in the failure when it is not done in time
    hups: int = 1


def run_with_operator(daemon: Daemon, offers: Sequence[Offer]) -> None:
    """``daemon.run()`` with its signal handlers installed, the offers made from a thread; the
    process's handlers restored after. Fails with what the operator saw go wrong."""
    failures: list[str] = []

    def operator() -> None:
        try:
            for offer in offers:
                while daemon.stats.frames_in < offer.after_frames:
                    time.sleep(0.001)
                offer.write()
                for _ in range(offer.hups):
                    os.kill(os.getpid(), signal.SIGHUP)
                end = time.monotonic() + RELOAD_TIMEOUT_S
                while not offer.done():
                    if time.monotonic() > end:
                        failures.append(f"{offer.what} not done within {RELOAD_TIMEOUT_S:g} s")
                        return
                    time.sleep(0.001)
        except Exception as exc:  # reported by the test, not lost in the thread
            failures.append(repr(exc))

    handlers = {s: signal.getsignal(s) for s in (signal.SIGHUP, signal.SIGTERM, signal.SIGINT)}
    daemon.install_signal_handlers()
    thread = threading.Thread(target=operator, daemon=True)
    try:
        thread.start()
        assert daemon.run() == 0
        thread.join(timeout=30)
    finally:
        for sig, handler in handlers.items():
            signal.signal(sig, handler)
    assert not failures, failures
