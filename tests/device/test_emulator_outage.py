"""``canical emulate`` rides out its bus going away, as the daemon does: no traceback, one log
line when the outage starts and one when it ends, a capped back-off between reopen attempts,
and the programme carries on when the bus is back.

The bus is a python-can interface registered for the test with the failure mode of a down
vcan (opening succeeds, every send and receive fails at once with "Network is down"), so the
real command runs on the host: its own ``open_network``, its reopen, its logging. On a real
vcan set down and up under the running command: the last test (marked vcan).
"""

from __future__ import annotations

import logging
import subprocess
import sys
import threading
import time
from pathlib import Path

import can
import pytest

from canical.commands.cli import main

pytestmark = pytest.mark.filterwarnings("error::pytest.PytestUnhandledThreadExceptionWarning")


class Link:
    """The interface as the kernel shows it: up or down; counts opens and frames sent."""

    def __init__(self) -> None:
        self.up = True
        self.opens = 0
        self.sent: list[tuple[float, int]] = []  # (monotonic time, frame id)


LINK = Link()


class FlakyBus(can.BusABC):
    """A python-can bus on :data:`LINK`: I/O fails with ENETDOWN while the link is down."""

    def __init__(self, channel: str, **kwargs: object) -> None:
        super().__init__(channel, **kwargs)
        self.channel_info = f"flaky {channel}"
        LINK.opens += 1

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if not LINK.up:
            raise can.CanOperationError("Network is down", error_code=100)
        LINK.sent.append((time.monotonic(), msg.arbitration_id))

    def _recv_internal(self, timeout: float | None):
        if not LINK.up:
            raise can.CanOperationError("Network is down", error_code=100)
        time.sleep(min(timeout or 0.0, 0.05))
        return None, False


@pytest.fixture
def flaky(monkeypatch):
    global LINK
    LINK = Link()
    monkeypatch.setitem(can.interfaces.BACKENDS, "canical-flaky", (__name__, "FlakyBus"))
    monkeypatch.setattr(can.util, "VALID_INTERFACES", can.util.VALID_INTERFACES | {"canical-flaky"})
    return LINK


def _emulate(tmp_path: Path, duration_s: float) -> int:
    return main(["emulate", "--interface", "canical-flaky", "--channel", "vcan0", "--rate", "100",
                 "--table", "still", "--duration", str(duration_s), "--state", str(tmp_path / "state.json")])


def test_emulate_rides_out_a_bus_outage(flaky: Link, tmp_path: Path, caplog, capfd) -> None:
    """Down 0.3 s after its first IMU frame, for 2.5 s: the command keeps running and exits 0, logs one line
    when the bus is lost (naming it and why) and one when it is back, reopens a handful of
    times (not hundreds), and sends the programme again afterwards."""
    caplog.set_level(logging.INFO, logger="canical.imu")
    times: dict[str, float] = {}

    def outage() -> None:
        start = time.monotonic()  # the command's imports take seconds on a loaded machine
        while not any(i == 0x190 for _, i in flaky.sent) and time.monotonic() - start < 60:
            time.sleep(0.02)
        time.sleep(0.3)
        times["down"] = time.monotonic()
        opens = flaky.opens
        flaky.up = False
        time.sleep(2.5)
        times["attempts"] = flaky.opens - opens
        flaky.up = True
        times["up"] = time.monotonic()

    toggler = threading.Thread(target=outage)
    toggler.start()
    status = _emulate(tmp_path, 6.0)
    toggler.join()
    assert status == 0
    err = capfd.readouterr().err
    assert "Traceback" not in err, err
    lines = [r.getMessage() for r in caplog.records if r.name == "canical.imu" and "vcan0" in r.getMessage()]
    assert len(lines) == 2, lines
    assert "canical-flaky vcan0 lost" in lines[0] and "Network is down" in lines[0], lines[0]
    assert "back after" in lines[1], lines[1]
    assert 2 <= times["attempts"] <= 12, f"{times['attempts']} reopen attempts in a 2.5 s outage"
    sent_during = [t for t, _ in flaky.sent if times["down"] < t < times["up"]]
    assert not sent_during
    after = [i for t, i in flaky.sent if t > times["up"]]
    assert 0x190 in after and 0x290 in after, "the IMU's frames did not resume"
    back = min(t for t, _ in flaky.sent if t > times["up"]) - times["up"]
    assert back <= 2.5, f"first frame {back:.1f} s after the bus came back (back-off is capped at 2 s)"


def test_emulate_stops_promptly_while_the_bus_is_down(flaky: Link, tmp_path: Path, capfd) -> None:
    """A bus down from the start and never back: the command still ends at --duration (a stop
    is served during the back-off), exits 0 and prints no traceback."""
    flaky.up = False
    start = time.monotonic()
    status = _emulate(tmp_path, 2.0)
    elapsed = time.monotonic() - start
    assert status == 0
    assert elapsed < 6.0, f"took {elapsed:.1f} s"
    assert "Traceback" not in capfd.readouterr().err


@pytest.mark.vcan
def test_vcan_emulate_survives_its_interface_going_down(vcan_channel: str, tmp_path: Path) -> None:
    """ip link down for 2 s under a streaming ``canical emulate``: it keeps running, streams
    again once the link is up, exits 0 on SIGTERM, and its stderr has the two outage lines
    and no traceback."""
    emulate = subprocess.Popen(
        [sys.executable, "-m", "canical", "emulate", "--interface", "socketcan", "--channel", vcan_channel,
         "--state", str(tmp_path / "state.json"), "--rate", "50", "--table", "still"],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    filters = [{"can_id": 0x190, "can_mask": 0x7FF, "extended": False}]  # IMU_RAW of node 0x10
    try:
        assert emulate.stdout is not None
        ready = emulate.stdout.readline()
        assert ready.startswith("ready"), (ready, emulate.poll() is not None and emulate.communicate())
        with can.Bus(interface="socketcan", channel=vcan_channel, can_filters=filters) as bus:
            assert bus.recv(10) is not None, "no IMU frame before the outage"
        subprocess.run(["ip", "link", "set", vcan_channel, "down"], check=True)
        time.sleep(2.0)
        subprocess.run(["ip", "link", "set", vcan_channel, "up"], check=True)
        with can.Bus(interface="socketcan", channel=vcan_channel, can_filters=filters) as bus:
            again = bus.recv(10)
        alive = emulate.poll() is None
    finally:
        emulate.terminate()
        _, err = emulate.communicate(timeout=30)
    assert alive, err
    assert again is not None, f"no IMU frame within 10 s of the link coming back: {err}"
    assert emulate.returncode == 0, err
    assert "Traceback" not in err, err
    assert f"socketcan {vcan_channel} lost" in err and "back after" in err, err
