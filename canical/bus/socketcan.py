"""The daemon's side of SocketCAN: frames as the kernel lays them out, the raw socket, sending.

python-can spends a ``select`` and two clock reads on each receive and each send; on a raw
CAN socket a frame costs one ``recvmsg`` and one ``send``. So on SocketCAN the daemon opens its
own raw socket (:func:`open_raw_socket`, set up as python-can's socketcan bus sets up its
own: CAN FD frames seen, error frames passed, nanosecond receive times, the kernel's filters)
and reads and writes frames in the kernel's layout; on other interfaces python-can is put
behind the same layout (:mod:`.link`), so one receive loop and one send path serve both.
A failure of the interface is :class:`BusLost`; a full transmit queue is not (the frame is
dropped and counted by the caller).
"""

from __future__ import annotations

import errno
import socket
import struct
from collections.abc import Iterable
from typing import Any

from can.interfaces.socketcan.constants import CAN_EFF_FLAG, CAN_RAW_ERR_FILTER

from canical.bus.socketcan_constants import CAN_ERR_MASK, FRAME_HEAD, SO_RCVBUFFORCE, SO_TIMESTAMPNS
from canical.frames.frame_match import FrameMatch

__all__ = ["RECEIVE_BUFFER_BYTES", "TX_FULL", "BusLost", "enlarge_socket_buffer",
           "frame_key", "kernel_filters", "open_raw_socket", "receive_filters", "socket_frame"]

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


def kernel_filters(matches: Iterable[FrameMatch]) -> bytes:
    """``CAN_RAW_FILTER``'s value passing exactly these frames (no match: no frame at all).

    As python-can builds it: each filter also compares the extended flag, so a standard id
    never passes for an extended one of the same number."""
    words: list[int] = []
    for m in dict.fromkeys(matches):
        words += [m.frame_id | (CAN_EFF_FLAG if m.extended else 0), m.mask | CAN_EFF_FLAG]
    return struct.pack(f"={len(words)}I", *words)


def open_raw_socket(channel: str, matches: Iterable[FrameMatch], *, fd_frames: bool = True) -> socket.socket:
    """A blocking raw CAN socket on ``channel`` receiving the frames ``matches`` name, CAN FD
    frames (the daemon's, to count and drop them; not with ``fd_frames`` off: a recorder's, as
    python-can's bus by default) and error frames, each with its receive time
    (``SO_TIMESTAMPNS``), and a receive buffer of seconds of frames. No match: send only.
    OSError when the channel cannot be bound."""
    sock = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    try:
        sock.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER, kernel_filters(matches))
        sock.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FD_FRAMES, int(fd_frames))
        sock.setsockopt(socket.SOL_CAN_RAW, CAN_RAW_ERR_FILTER, CAN_ERR_MASK)
        sock.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
        enlarge_socket_buffer(sock)  # a moment's stall of the host loses no frame
        sock.bind((channel,))
    except OSError:
        sock.close()
        raise
    return sock


def enlarge_socket_buffer(sock: socket.socket, size_bytes: int = RECEIVE_BUFFER_BYTES) -> bool:
    """Ask for a receive buffer of ``size_bytes`` on a socket: beyond the system's cap where the
    process may (``SO_RCVBUFFORCE``), within it otherwise (the kernel then grants up to
    ``net.core.rmem_max``). False: refused; the default buffer stays."""
    for option in (SO_RCVBUFFORCE, socket.SO_RCVBUF):
        try:
            sock.setsockopt(socket.SOL_SOCKET, option, size_bytes)
        except OSError:
            continue
        return True
    return False
