"""The recorders' bus: on SocketCAN canical's own raw socket behind python-can's public ``BusABC``.

Why: a recorder busy decoding or writing its log must not lose frames, so it asks for a receive
buffer of seconds of frames. python-can's socketcan bus keeps its socket in a non-public
attribute; reaching into it would tie canical to python-can's internals. The daemon already
opens its own raw socket (:func:`~canical.bus.socketcan.open_raw_socket`); the recorders open
the same socket and read it through a small :class:`can.BusABC` (the documented way to add an
interface), so ``can.Logger``, ``recv`` with a timeout and ``with`` work as they did. Frames
are read as python-can's socketcan bus reads them: its filters' meaning, error frames passed,
no CAN FD frames, no frames of its own, the kernel's receive time. Other interfaces, or
interface options only python-can understands, get python-can's own bus.
"""

from __future__ import annotations

import select
import socket
from collections.abc import Iterable
from typing import Any

import can
from can.interfaces.socketcan.constants import (
    CAN_EFF_FLAG,
    CAN_ERR_FLAG,
    CAN_RTR_FLAG,
    CANFD_BRS,
    CANFD_ESI,
    CANFD_MTU,
)

from canical.bus.socketcan import open_raw_socket, receive_filters, socket_frame
from canical.bus.socketcan_constants import FRAME_HEAD, SO_TIMESTAMPNS, STAMP_BUFFER_SIZE, TIMEVAL
from canical.frames.frame_match import FrameMatch

__all__ = ["RawSocketBus", "open_receive_bus"]


class RawSocketBus(can.BusABC):
    """The frames ``matches`` name on ``channel``, as :class:`can.Message`."""

    def __init__(self, channel: str, matches: Iterable[FrameMatch]) -> None:
        self.socket = open_raw_socket(channel, matches, fd_frames=False)  # OSError: as python-can's
        self.channel_name = channel  # each message's, as python-can's socketcan bus names it
        self.channel_info = f"canical raw socket on {channel}"
        super().__init__(channel)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        """The next frame, or None after ``timeout`` (the kernel filtered already: True)."""
        try:
            ready, _, _ = select.select([self.socket], [], [], timeout)
            if not ready:
                return None, True
            frame, ancillary, flags, _ = self.socket.recvmsg(CANFD_MTU, STAMP_BUFFER_SIZE)
        except OSError as exc:
            raise can.CanOperationError(f"Error receiving: {exc.strerror}", exc.errno) from exc
        return message(frame, ancillary, flags, self.channel_name), True

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """A classic frame out, never waiting (``timeout`` is not used): the recorders only
        receive, but a bus must be able to send."""
        frame = socket_frame(msg.arbitration_id, msg.is_extended_id, bytes(msg.data))
        try:
            self.socket.send(frame, socket.MSG_DONTWAIT)
        except OSError as exc:
            raise can.CanOperationError(f"Failed to transmit: {exc.strerror}", exc.errno) from exc

    def shutdown(self) -> None:
        super().shutdown()
        self.socket.close()


def message(frame: bytes, ancillary: list[tuple[int, int, bytes]], flags: int, channel: str) -> can.Message:
    """A kernel frame as python-can's socketcan bus gives it: the flags as fields, the receive
    time from ``SO_TIMESTAMPNS``, received (not sent here) unless ``MSG_DONTROUTE``."""
    can_id, length, fd_flags, _ = FRAME_HEAD.unpack_from(frame)
    extended = bool(can_id & CAN_EFF_FLAG)
    stamp = 0.0
    for level, kind, data in ancillary:
        if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS:
            seconds, nanoseconds = TIMEVAL.unpack_from(data)
            stamp = seconds + nanoseconds * 1e-9
    return can.Message(
        timestamp=stamp,
        channel=channel,
        arbitration_id=can_id & (0x1FFFFFFF if extended else 0x7FF),
        is_extended_id=extended,
        is_remote_frame=bool(can_id & CAN_RTR_FLAG),
        is_error_frame=bool(can_id & CAN_ERR_FLAG),
        is_fd=len(frame) == CANFD_MTU,
        is_rx=not flags & socket.MSG_DONTROUTE,
        bitrate_switch=bool(fd_flags & CANFD_BRS),
        error_state_indicator=bool(fd_flags & CANFD_ESI),
        dlc=length,
        data=frame[FRAME_HEAD.size:FRAME_HEAD.size + length],
    )


def open_receive_bus(interface: str, channel: str, matches: Iterable[FrameMatch],
                     **options: Any) -> can.BusABC:
    """A bus receiving the frames ``matches`` name: on SocketCAN without options canical's raw
    socket, with its large receive buffer (:class:`RawSocketBus`); else python-can's bus with the
    same filters and ``options`` (python-can's keyword arguments, typed by it: Any)."""
    if interface == "socketcan" and not options:
        return RawSocketBus(channel, matches)
    return can.Bus(interface=interface, channel=channel, can_filters=receive_filters(matches), **options)
