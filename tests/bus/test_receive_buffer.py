"""A reader of the IMU's frames (the recorder, the daemon) asks for a receive buffer of seconds of
frames, so that a moment's stall of its host loses nothing: on a real SocketCAN, a burst far
beyond the kernel's default buffer, sent while the reader does not read, all arrives."""

from __future__ import annotations

import socket

import pytest

from canical.bus.recording import open_recorder_bus
from canical.bus.socketcan import RECEIVE_BUFFER_BYTES, enlarge_receive_buffer, socket_frame
from canical.frames.imu_frames import ImuFrames

BURST = 3000  # frames: the default buffer (net.core.rmem_default, ~200 kB) holds a few hundred


def test_a_bus_without_a_socketcan_socket_is_left_as_it_is() -> None:
    import can

    with can.Bus(interface="virtual", channel="buffer-test") as bus:
        assert enlarge_receive_buffer(bus) is False


@pytest.mark.vcan
def test_recorder_bus_keeps_a_burst_it_did_not_read_in_time(vcan_channel: str) -> None:
    frames = ImuFrames(0x10)
    raw_id = frames.ids["IMU_RAW"]
    with open_recorder_bus("socketcan", vcan_channel, frames) as bus:
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
