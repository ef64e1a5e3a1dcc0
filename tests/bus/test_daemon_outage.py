"""The daemon's periodic step while the bus is gone: watchdog, back-off, outage log and STATUS.

The bus is an in-process stand-in with the failure mode of a down vcan (opening succeeds, every
send and receive fails at once), so the timing of a multi-second outage is checked on the host
in a few seconds; the same under systemd on a real vcan is in test_systemd_guest.py.
"""

from __future__ import annotations

import itertools
import logging
import threading
import time
from pathlib import Path

import can
import pytest
from support.daemon_fixtures import DBC, NotifyListener, write_config, write_sets

from canical.bus.daemon import Daemon
from canical.bus.daemon_config import load_config
from canical.bus.link import BusLink
from canical.bus.sd_notify import Notifier
from canical.frames.codec import StatusEncoder, load_dbc

WATCHDOG_USEC = 400_000  # pings due every 0.2 s


class Link:
    """The interface as the kernel shows it: up or down; counts how often it was opened."""

    def __init__(self) -> None:
        self.up = True
        self.opens = 0
        self.block = threading.Event()  # set: recv hangs (a blocked loop, not a dead bus)
        self.sent: list[can.Message] = []

    def factory(self, **_: object) -> FlakyBus:
        self.opens += 1
        return FlakyBus(self)


class FlakyBus:
    """Binding succeeds even when the link is down (as on vcan); I/O then fails with ENETDOWN."""

    def __init__(self, link: Link) -> None:
        self.link = link

    def _check(self) -> None:
        if not self.link.up:
            raise can.CanOperationError("Network is down", error_code=100)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        self._check()
        self.link.sent.append(msg)

    def recv(self, timeout: float | None = None) -> can.Message | None:
        while self.link.block.is_set():
            time.sleep(0.01)
        self._check()
        time.sleep(timeout or 0.0)
        return None

    def shutdown(self) -> None:
        pass


@pytest.fixture
def running(tmp_path: Path):
    """A daemon serving a Link in a thread, with a notify socket and a 0.4 s watchdog."""
    write_sets(tmp_path)
    config = load_config(write_config(tmp_path, "vcan0", status_period_s=0.2))
    listener = NotifyListener()
    link = Link()
    daemon = Daemon(config, open_link=lambda channel, matches: BusLink(link.factory()),  # type: ignore[arg-type]
                    notifier=Notifier({"NOTIFY_SOCKET": listener.name, "WATCHDOG_USEC": str(WATCHDOG_USEC)}))
    thread = threading.Thread(target=daemon.run, daemon=True)
    thread.start()
    listener.wait_for("READY", 30)
    yield daemon, link, listener
    link.block.clear()
    daemon.request_stop()
    thread.join(10)
    listener.close()
    assert not thread.is_alive()


def test_outage_keeps_watchdog_backs_off_and_logs_three_lines(running, caplog) -> None:
    """A 3 s outage: pings keep coming within the watchdog interval, a handful of reopen
    attempts (not hundreds), STATUS says the channel is down, the log has a start and an end
    line (with the duration), and the outage counts once."""
    daemon, link, listener = running
    caplog.set_level(logging.INFO, logger="canical.serve")
    time.sleep(0.5)
    opens_before, t_down = link.opens, time.monotonic()
    link.up = False
    time.sleep(3.0)
    link.up = True
    t_up = time.monotonic()
    deadline = t_up + 5
    while daemon.outage is not None and time.monotonic() < deadline:
        time.sleep(0.05)
    assert daemon.outage is None, "the daemon never noticed the bus was back"
    back = time.monotonic() - t_up
    pings = [t for t in listener.arrivals("WATCHDOG") if t_down - 0.5 <= t <= t_up + back]
    gaps = [b - a for a, b in itertools.pairwise(pings)]
    assert max(gaps) < WATCHDOG_USEC / 1e6, f"watchdog silent for {max(gaps):.2f} s during the outage"
    attempts = link.opens - opens_before
    assert 3 <= attempts <= 12, f"{attempts} reopen attempts in a 3 s outage"
    assert back <= 2.5  # the back-off is capped at 2 s
    statuses = [m["STATUS"] for t, m in zip(listener.times, listener.messages, strict=False)
                if "STATUS" in m and t_down < t < t_up]
    assert statuses and all("vcan0 down for" in s for s in statuses), statuses
    outage_lines = [r.getMessage() for r in caplog.records if "vcan0" in r.getMessage()]
    assert len(outage_lines) == 2, outage_lines
    assert "lost" in outage_lines[0] and "Network is down" in outage_lines[0]
    assert "back after 3." in outage_lines[1] or "back after 4." in outage_lines[1], outage_lines[1]
    assert daemon.stats.bus_restarts == 1
    assert "down for" not in listener.messages[-1].get("STATUS", "")


def test_blocked_loop_stops_pinging(running) -> None:
    """The watchdog watches the loop: a receive that hangs (the process is not stopped) means
    no more pings, so systemd's watchdog fires."""
    _, link, listener = running
    time.sleep(0.5)
    link.block.set()
    time.sleep(0.3)  # a receive already in progress may finish and ping once more
    before = len(listener.arrivals("WATCHDOG"))
    time.sleep(1.2)  # three watchdog intervals
    assert len(listener.arrivals("WATCHDOG")) == before
    link.block.clear()
    time.sleep(0.6)
    assert len(listener.arrivals("WATCHDOG")) > before  # and it resumes when the loop does


@pytest.mark.parametrize("count", [0, 254, 255, 256, 1743, 70_000])
def test_fault_counters_saturate_frame_counters_wrap(count: int) -> None:
    """Page 2 (faults) holds at 255, so 1,743 bus restarts never read as 207; page 0's frame
    counters keep wrapping (receivers take differences)."""
    msg = load_dbc(DBC).get_message_by_name("CANICAL_STATUS")
    enc = StatusEncoder(msg)
    page2 = msg.decode(enc.encode(2, {"BusRestarts": count, "TxDropped": count}, saturate=True),
                       decode_choices=False)
    assert page2["BusRestarts"] == page2["TxDropped"] == min(count, 255)
    page0 = msg.decode(enc.encode(0, {"FramesIn": count}), decode_choices=False)
    assert page0["FramesIn"] == count % 65_536


def test_daemon_status_frame_saturates_bus_restarts(running) -> None:
    daemon, link, _ = running
    daemon.stats.bus_restarts = 1743
    msg = load_dbc(DBC).get_message_by_name("CANICAL_STATUS")
    n = len(link.sent)
    deadline = time.monotonic() + 5
    while time.monotonic() < deadline:
        pages = [msg.decode(m.data, decode_choices=False) for m in link.sent[n:]
                 if m.arbitration_id == msg.frame_id]
        page2 = [p for p in pages if p["Page"] == 2]
        if page2:
            assert page2[-1]["BusRestarts"] == 255
            return
        time.sleep(0.05)
    raise AssertionError("no status page 2 sent")
