"""SocketCAN's frame layout where python-can's public constants do not name it (``<linux/can.h>``).

The flags in ``can_id``'s top bits, the CAN FD frame's size and the id masks come from
:mod:`can.interfaces.socketcan.constants`; what reading and writing the raw socket directly
needs beyond those is named here, so nothing imports python-can's private module internals.
"""

from __future__ import annotations

import socket
import struct

from can.interfaces.socketcan.constants import CAN_EFF_FLAG, MAX_29_BIT_ID

__all__ = ["CAN_ERR_MASK", "CAN_MTU", "FRAME_HEAD", "FRAME_KEY", "SO_RCVBUFFORCE", "SO_TIMESTAMPNS",
           "STAMP_BUFFER_SIZE", "TIMEVAL"]

#: ``sizeof(struct can_frame)``: a classic frame as the raw socket reads and writes it.
CAN_MTU = 16
#: The head of ``struct can_frame`` / ``canfd_frame``: can_id (flags included), len, flags,
#: len8_dlc; the data follow from byte 8.
FRAME_HEAD = struct.Struct("=IBB1xB")
#: Two C longs: ``struct timeval`` (``SO_RCVTIMEO``) and ``struct timespec`` (the
#: ``SO_TIMESTAMPNS`` receive time) alike.
TIMEVAL = struct.Struct("@ll")
#: Room for the receive time's control message in ``recvmsg`` (0 where the platform has none).
STAMP_BUFFER_SIZE = socket.CMSG_SPACE(TIMEVAL.size) if hasattr(socket, "CMSG_SPACE") else 0
#: What tells frames apart: the id and whether it is extended (not the RTR and error flags).
FRAME_KEY = CAN_EFF_FLAG | MAX_29_BIT_ID
#: ``SO_RCVBUFFORCE`` (``<asm-generic/socket.h>``; Python's socket module does not name it): a
#: receive buffer beyond ``net.core.rmem_max``, for a process with CAP_NET_ADMIN.
SO_RCVBUFFORCE = getattr(socket, "SO_RCVBUFFORCE", 33)
#: ``SO_TIMESTAMPNS`` (``<asm-generic/socket.h>``): each received frame's kernel receive time, in ns.
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)
#: ``CAN_ERR_MASK`` (``<linux/can/error.h>``): every class of error frame, for ``CAN_RAW_ERR_FILTER``.
CAN_ERR_MASK = 0x1FFFFFFF
