"""The daemon's side of SocketCAN: frames as the kernel lays them out, the raw socket, sending.

python-can spends a ``select`` and two clock reads on each receive and each send; on the
socketcan bus's own raw socket a frame costs one ``recvmsg`` and one ``send``. The daemon
uses that socket directly when it can (:func:`raw_socket_of`) and python-can's ``recv`` and
``send`` otherwise; either way a frame is named by its ``can_id`` with SocketCAN's flag bits,
so one classification serves both. A failure of the interface is :class:`BusLost`; a full
transmit queue is not (the frame is dropped and counted by the caller).
"""

from __future__ import annotations

import errno
import socket
from collections.abc import Iterable
from typing import Any

import can
from can.interfaces.socketcan.constants import CAN_EFF_FLAG

from canical.bus.socketcan_constants import FRAME_HEAD, SO_RCVBUFFORCE, TIMEVAL
from canical.frames.frame_match import FrameMatch

__all__ = ["RECEIVE_BUFFER_BYTES", "TX_FULL", "BusLost", "enlarge_receive_buffer", "frame_key",
           "raw_socket_of", "receive_filters", "send_message", "set_receive_timeout", "socket_frame"]

#: errno values that mean "not a problem of this frame": the transmit queue is full.
TX_FULL = frozenset({errno.ENOBUFS, errno.EAGAIN})


#: The receive buffer a reader of the IMU's frames asks for: a few thousand frames (a CAN frame
#: takes some 700-1000 bytes of kernel memory), seconds of a 1 kHz IMU, so that a reader the
#: host stalls for a moment loses nothing (the kernel's default holds a few hundred).
RECEIVE_BUFFER_BYTES = 4 << 20


class BusLost(Exception):
    """The interface failed under us; reopen it."""


def frame_key(frame_id: int, extended: bool) -> int:
    """A frame's id as the kernel's ``can_id`` carries it (the extended flag included)."""
    return frame_id | (CAN_EFF_FLAG if extended else 0)


def socket_frame(frame_id: int, extended: bool, payload: bytes) -> bytes:
    """A classic frame as the kernel takes it on a raw CAN socket."""
    return FRAME_HEAD.pack(frame_key(frame_id, extended), len(payload), 0, 0) + payload.ljust(8, b"\0")


def receive_filters(matches: Iterable[FrameMatch]) -> list[dict[str, Any]]:
    """python-can's ``can_filters`` passing exactly these frames: an id, or a J1939 group's ids."""
    unique = dict.fromkeys(matches)
    return [{"can_id": m.frame_id, "can_mask": m.mask, "extended": m.extended} for m in unique]


def raw_socket_of(bus: object) -> socket.socket | None:
    """The bus's own SocketCAN socket when frames can go through it directly, else None.

    Only python-can's socketcan bus has one (``bus.socket``); it must be a blocking socket
    (python-can's default), so that the receive timeout set below is the wait.
    """
    sock = getattr(bus, "socket", None)
    usable = sock is not None and getattr(sock, "family", None) == socket.AF_CAN and sock.gettimeout() is None
    return sock if usable else None


def enlarge_receive_buffer(bus: object, size_bytes: int = RECEIVE_BUFFER_BYTES) -> bool:
    """Ask for a receive buffer of ``size_bytes`` on the bus's SocketCAN socket: beyond the
    system's cap where the process may (``SO_RCVBUFFORCE``), within it otherwise (the kernel
    then grants up to ``net.core.rmem_max``). False: not a SocketCAN bus, or refused; the
    default buffer stays."""
    sock = getattr(bus, "socket", None)
    if sock is None or getattr(sock, "family", None) != socket.AF_CAN:
        return False
    for option in (SO_RCVBUFFORCE, socket.SO_RCVBUF):
        try:
            sock.setsockopt(socket.SOL_SOCKET, option, size_bytes)
        except OSError:
            continue
        return True
    return False


def set_receive_timeout(sock: socket.socket, wait_s: float) -> float:
    """Make ``recvmsg`` on ``sock`` give up after ``wait_s``; returns the timeout as set."""
    usec = max(1, int(wait_s * 1e6))  # 0 would mean "wait for ever"
    try:
        sock.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO, TIMEVAL.pack(*divmod(usec, 1_000_000)))
    except OSError as exc:
        raise BusLost(f"receive failed: {exc}") from None
    return usec * 1e-6


def send_message(bus: can.BusABC, frame_id: int, extended: bool, payload: bytes) -> bool:
    """One frame through python-can's ``send``: False when the transmit queue was full (the frame
    is dropped), :class:`BusLost` when the interface failed."""
    try:
        bus.send(can.Message(arbitration_id=frame_id, is_extended_id=extended, data=payload, check=False))
    except can.CanOperationError as exc:
        if exc.error_code in TX_FULL or "buffer full" in str(exc):
            return False
        raise BusLost(f"send failed: {exc}") from None
    except can.CanError as exc:
        raise BusLost(f"send failed: {exc}") from None
    return True
