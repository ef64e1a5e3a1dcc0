"""A reader of the IMU's frames (the recorder, the daemon) asks for a receive buffer of seconds of
frames, so that a moment's stall of its host loses nothing: on a real SocketCAN, a burst far
beyond the kernel's default buffer, sent while the reader does not read, all arrives."""

from __future__ import annotations

import socket

import pytest

from canical.bus.raw_bus import RawSocketBus, message
from canical.bus.recording import open_recorder_bus
from canical.bus.socketcan import RECEIVE_BUFFER_BYTES, socket_frame
from canical.bus.socketcan_constants import SO_TIMESTAMPNS, TIMEVAL
from canical.frames.imu_frames import ImuFrames

BURST = 3000  # frames: the default buffer (net.core.rmem_default, ~200 kB) holds a few hundred


def test_another_interface_is_python_cans_own_bus() -> None:
    with open_recorder_bus("virtual", "buffer-test", ImuFrames(0x10)) as bus:
        assert not isinstance(bus, RawSocketBus)


def test_a_kernel_frame_reads_as_python_cans_socketcan_bus_reads_it() -> None:
    """Id and flags, length, data and the kernel's receive time, as ``can.Logger`` writes them."""
    stamp = [(socket.SOL_SOCKET, SO_TIMESTAMPNS, TIMEVAL.pack(1700000000, 250_000_000))]
    msg = message(socket_frame(0x18FF0080, True, bytes([1, 2, 3])), stamp, 0, "vcan9")
    assert (msg.arbitration_id, msg.is_extended_id, msg.dlc) == (0x18FF0080, True, 3)
    assert bytes(msg.data) == b"\1\2\3"
    assert (msg.timestamp, msg.channel, msg.is_rx) == (1700000000.25, "vcan9", True)
    assert not (msg.is_fd or msg.is_error_frame or msg.is_remote_frame)
    standard = message(socket_frame(0x123, False, bytes(8)), stamp, socket.MSG_DONTROUTE, "vcan9")
    assert (standard.arbitration_id, standard.is_extended_id, standard.is_rx) == (0x123, False, False)


@pytest.mark.vcan
def test_recorder_bus_keeps_a_burst_it_did_not_read_in_time(vcan_channel: str) -> None:
    frames = ImuFrames(0x10)
    raw_id = frames.ids["IMU_RAW"]
    with open_recorder_bus("socketcan", vcan_channel, frames) as bus:
        assert isinstance(bus, RawSocketBus)  # canical's own socket: no python-can internals
        assert bus.socket.getsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF) >= RECEIVE_BUFFER_BYTES
        with socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW) as tx:
            tx.bind((vcan_channel,))
            for i in range(BURST):
                frame = socket_frame(raw_id, False, i.to_bytes(2, "little") + bytes(6))
                while True:
                    try:
                        tx.send(frame)
                        break
                    except OSError:  # the sender's own queue is full: let it drain
                        continue
        got = []
        while (msg := bus.recv(timeout=1.0)) is not None:
            got.append(int.from_bytes(msg.data[:2], "little"))
    assert got == list(range(BURST))
