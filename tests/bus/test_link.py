"""The daemon's links: python-can behind a raw socket's calls gives exactly the kernel's frames,
and the kernel filters canical sets on its own socket are python-can's."""

from __future__ import annotations

import errno
import socket
import struct

import can
import pytest
from hypothesis import given
from hypothesis import strategies as st
from test_daemon_compiled import kernel_frame

from canical.bus.link import BusLink, Sender
from canical.bus.socketcan import BusLost, kernel_filters, receive_filters
from canical.bus.socketcan_constants import SO_TIMESTAMPNS, TIMEVAL
from canical.bus.status import Stats
from canical.frames.frame_match import FrameMatch


class OneBus:
    """Hands out one message, then nothing; keeps what is sent; fails as told."""

    def __init__(self, msg: can.Message | None = None, fail: can.CanError | None = None) -> None:
        self.msg, self.fail, self.sent = msg, fail, list[can.Message]()

    def recv(self, timeout: float | None = None) -> can.Message | None:
        if self.fail is not None:
            raise self.fail
        msg, self.msg = self.msg, None
        return msg

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.fail is not None:
            raise self.fail
        self.sent.append(msg)


messages = st.builds(
    lambda ext, fid, data, fd, stamp: can.Message(
        arbitration_id=fid & (0x1FFFFFFF if ext else 0x7FF), is_extended_id=ext, data=data, is_fd=fd,
        timestamp=stamp, check=False),
    st.booleans(), st.integers(0, 0x1FFFFFFF), st.binary(max_size=8), st.booleans(),
    st.floats(0.0, 1e6, allow_nan=False))


@given(msg=messages)
def test_a_message_is_the_kernels_frame_with_its_receive_time(msg: can.Message) -> None:
    frame, anc, _, _ = BusLink(OneBus(msg)).recvmsg(72, 32)  # type: ignore[arg-type]
    assert frame == kernel_frame(msg)
    ((level, kind, data),) = anc
    sec, nsec = TIMEVAL.unpack(data)
    assert (level, kind) == (socket.SOL_SOCKET, SO_TIMESTAMPNS) and 0 <= nsec < 1_000_000_000
    assert abs(sec + nsec * 1e-9 - msg.timestamp) <= 1e-9 + 1e-15 * msg.timestamp


@given(msg=messages.filter(lambda m: not m.is_fd))
def test_a_sent_frame_is_the_message_again(msg: can.Message) -> None:
    bus = OneBus()
    BusLink(bus).send(kernel_frame(msg), 0)  # type: ignore[arg-type]
    (sent,) = bus.sent
    assert (sent.arbitration_id, sent.is_extended_id, bytes(sent.data)) == (
        msg.arbitration_id, msg.is_extended_id, bytes(msg.data))


def test_nothing_in_the_wait_is_the_sockets_timeout_and_a_failure_is_bus_lost() -> None:
    with pytest.raises(BlockingIOError):
        BusLink(OneBus()).recvmsg(72, 32)  # type: ignore[arg-type]
    with pytest.raises(BusLost, match="receive failed: Network is down"):
        BusLink(OneBus(fail=can.CanOperationError("Network is down"))).recvmsg(72, 32)  # type: ignore[arg-type]


def test_a_full_queue_drops_and_counts_a_failure_loses_the_bus() -> None:
    stats = Stats()
    sender = Sender(stats)
    frame = kernel_frame(can.Message(arbitration_id=0x10, data=b"\1", is_extended_id=False))
    sender.link = BusLink(OneBus(fail=can.CanOperationError("Transmit buffer full",  # type: ignore[arg-type]
                                                            error_code=errno.ENOBUFS)))
    sender.send(frame)
    assert stats.tx_dropped == 1
    sender.link = BusLink(OneBus(fail=can.CanOperationError("Network is down", error_code=100)))  # type: ignore[arg-type]
    with pytest.raises(BusLost, match="send failed"):
        sender.send(frame)
    sender.link = None
    sender.send(frame)  # the bus is down: nothing to send on, nothing counted
    assert stats.tx_dropped == 1


def test_kernel_filters_are_python_cans() -> None:
    """The words python-can's socketcan bus sets for the same ``can_filters`` (its
    ``_apply_filters``: the extended flag in id and mask), one filter per distinct match."""
    matches = [FrameMatch(0x190, False, 0x7FF), FrameMatch(0x00FF2A00, True, 0x03FFFF00),
               FrameMatch(0x190, False, 0x7FF)]
    words = []
    for f in receive_filters(matches):
        flag = socket.CAN_EFF_FLAG
        words += [f["can_id"] | (flag if f["extended"] else 0), f["can_mask"] | flag]
    assert kernel_filters(matches) == struct.pack("=4I", *words)
    assert kernel_filters([]) == b""  # no filter: the socket receives nothing (send only)



def test_socketcan_options_keep_python_cans_bus(tmp_path, monkeypatch: pytest.MonkeyPatch) -> None:
    """``bus.options`` are python-can's keyword arguments: with them the link is python-can's bus
    (which honours them), without them on SocketCAN canical's own raw socket."""
    from support.daemon_fixtures import write_config, write_sets

    from canical.bus import link
    from canical.bus.daemon_config import load_config

    write_sets(tmp_path)
    buses: list[dict[str, object]] = []
    sockets: list[str] = []

    class StandIn:
        recvmsg = send = None

    monkeypatch.setattr(link.can, "Bus", lambda **kwargs: buses.append(kwargs) or StandIn())
    monkeypatch.setattr(link, "open_raw_socket", lambda channel, _: sockets.append(channel) or StandIn())
    plain = load_config(write_config(tmp_path, "can7"))
    assert isinstance(link.opener(plain, compiled=True)("can7", []), link.SocketLink)
    assert isinstance(link.opener(plain, compiled=False)("can7", []), link.BusLink)  # the reference path
    options = {"interface": "socketcan", "channel": "can8", "options": {"receive_own_messages": True}}
    with_options = load_config(write_config(tmp_path, "can8", bus=options))
    assert isinstance(link.opener(with_options, compiled=True)("can8", []), link.BusLink)
    assert sockets == ["can7"] and buses[-1]["receive_own_messages"] is True


def test_more_than_eight_bytes_is_an_fd_frame_whatever_the_message_says() -> None:
    msg = can.Message(arbitration_id=0x10, data=bytes(range(12)), is_extended_id=False, is_fd=False,
                      check=False)
    frame, _, _, _ = BusLink(OneBus(msg)).recvmsg(72, 32)  # type: ignore[arg-type]
    assert len(frame) == 72 and frame[4] == 12 and frame[8:20] == bytes(range(12)) and not any(frame[20:])
