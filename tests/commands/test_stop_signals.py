"""A paced loop stopped by SIGTERM stops, whenever in its wait the signal lands.

``canical emulate`` waits on its stop event between samples; its SIGTERM handler used to set that
event itself and, now and then, hung forever (the handler ran while the main thread held the
event's lock). A child that does nothing but wait on the event makes the window wide: with a
handler that sets the event, most of these children hang; each must stop here.
"""

from __future__ import annotations

import signal
import subprocess
import sys
import threading
import time

from canical.commands.stop_signals import event_on_signals

BUSY_WAITER = """
import threading
from canical.commands.stop_signals import event_on_signals
stop = threading.Event()
with event_on_signals(stop):
    print("ready", flush=True)
    while not stop.is_set():
        stop.wait(0)
print("stopped", flush=True)
"""


def test_a_loop_waiting_on_the_event_stops_at_every_sigterm() -> None:
    children = [subprocess.Popen([sys.executable, "-c", BUSY_WAITER], stdout=subprocess.PIPE, text=True)
                for _ in range(12)]
    try:
        for child in children:
            assert child.stdout is not None and child.stdout.readline() == "ready\n"
        time.sleep(0.05)
        for child in children:
            child.send_signal(signal.SIGTERM)
        outs = [child.communicate(timeout=20)[0] for child in children]
    finally:
        for child in children:
            child.kill()
    assert [(c.returncode, out) for c, out in zip(children, outs, strict=True)] == [(0, "stopped\n")] * 12


def test_the_handlers_are_restored_after_the_block() -> None:
    """Whatever handled SIGINT before the block handles it after; within it, it sets the event.
    (The handler before is the test's own: another test may have left the process's otherwise.)"""
    seen: list[int] = []
    ambient = signal.getsignal(signal.SIGINT)
    signal.signal(signal.SIGINT, lambda signum, _frame: seen.append(signum))
    try:
        before = signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)
        stop = threading.Event()
        with event_on_signals(stop):
            signal.raise_signal(signal.SIGINT)
            assert stop.wait(5.0)
        assert seen == []
        assert (signal.getsignal(signal.SIGTERM), signal.getsignal(signal.SIGINT)) == before
        assert signal.set_wakeup_fd(-1) == -1  # none left set
        signal.raise_signal(signal.SIGINT)
        assert seen == [signal.SIGINT]
    finally:
        signal.signal(signal.SIGINT, ambient)
