"""The daemon's handle on one CAN interface: frames in the kernel's layout, in and out.

Why one layout: the hot path is a raw CAN socket's ``recvmsg`` and ``send`` (:mod:`.socketcan`);
putting python-can behind the same two calls (:class:`BusLink`, for the interfaces that are not
SocketCAN and for the reference path) leaves the daemon one receive loop, one classification
of frames and one send path, whatever the interface. The cost of the translation falls only
on python-can's side, which spends more than that on its own ``recv`` anyway.
"""

from __future__ import annotations

import errno
import logging
import socket
import struct
from collections.abc import Callable, Iterable
from socket import MSG_DONTWAIT
from typing import Any

import can
from can.interfaces.socketcan.constants import CAN_EFF_FLAG, CAN_ERR_FLAG, CAN_RTR_FLAG, CANFD_MTU

from canical.bus.daemon_config import DaemonConfig
from canical.bus.socketcan import TX_FULL, BusLost, open_raw_socket, receive_filters
from canical.bus.socketcan_constants import CAN_MTU, FRAME_HEAD, SO_TIMESTAMPNS, TIMEVAL
from canical.bus.status import Stats
from canical.frames.frame_match import FrameMatch

__all__ = ["BusLink", "Link", "LinkOpener", "Sender", "SocketLink", "opener"]

log = logging.getLogger("canical.serve")

_HEAD = FRAME_HEAD.size
_DATA, _FD_DATA = CAN_MTU - _HEAD, CANFD_MTU - _HEAD  # data bytes in a frame
#: A whole frame in one call: the head, then the data padded with zeros to the classic or FD size.
_pack_classic = struct.Struct(f"{FRAME_HEAD.format}{_DATA}s").pack
_pack_fd = struct.Struct(f"{FRAME_HEAD.format}{_FD_DATA}s").pack
_SECOND, _LAST_NS = 1_000_000_000, 999_999_999
_EFF_MASK, _SFF_MASK = 0x1FFFFFFF, 0x7FF
_unpack_head, _pack_stamp, _SOL_SOCKET = FRAME_HEAD.unpack_from, TIMEVAL.pack, socket.SOL_SOCKET
_Message = can.Message

#: ``recvmsg``'s result: the frame, the ancillary data (the receive time), flags, address.
Received = tuple[bytes, list[tuple[int, int, bytes]], int, Any]


class SocketLink:
    """A raw CAN socket (:func:`~canical.bus.socketcan.open_raw_socket`): its own ``recvmsg``
    and ``send``, bound once, so a frame costs exactly those calls."""

    def __init__(self, sock: socket.socket) -> None:
        self.socket = sock
        self.recvmsg: Callable[[int, int], Received] = sock.recvmsg
        self.send: Callable[[bytes, int], int] = sock.send
        self._timeout = -1.0

    def set_wait(self, wait_s: float) -> None:
        """Make ``recvmsg`` give up after about ``wait_s`` (``SO_RCVTIMEO``): set only when the
        wait has become shorter than the timeout set (or much longer), so at most once per
        burst of frames and rarely at all."""
        if wait_s < self._timeout or wait_s > 2.0 * self._timeout:
            usec = max(1, int(wait_s * 1e6))  # 0 would mean "wait for ever"
            try:
                self.socket.setsockopt(socket.SOL_SOCKET, socket.SO_RCVTIMEO,
                                       TIMEVAL.pack(*divmod(usec, 1_000_000)))
            except OSError as exc:
                raise BusLost(f"receive failed: {exc}") from None
            self._timeout = usec * 1e-6

    def close(self) -> None:
        self.socket.close()


class BusLink:
    """A python-can bus behind a raw socket's ``recvmsg`` and ``send``: messages become kernel
    frames (the id with its flag bits, the classic or FD size) and back."""

    def __init__(self, bus: can.BusABC) -> None:
        self.bus = bus
        self._wait = 0.0

    def set_wait(self, wait_s: float) -> None:
        self._wait = wait_s

    def recvmsg(self, bufsize: int = CANFD_MTU, ancbufsize: int = 0) -> Received:
        """The next message as the kernel lays it out; BlockingIOError when none came in the
        wait, :class:`BusLost` when the interface failed."""
        try:
            msg = self.bus.recv(self._wait)
        except can.CanError as exc:
            raise BusLost(f"receive failed: {exc}") from None
        if msg is None:
            raise BlockingIOError(errno.EAGAIN, "no frame")
        can_id = msg.arbitration_id
        if msg.is_extended_id:
            can_id |= CAN_EFF_FLAG
        if msg.is_remote_frame:
            can_id |= CAN_RTR_FLAG
        if msg.is_error_frame:
            can_id |= CAN_ERR_FLAG
        data = msg.data
        size = len(data)  # more than 8 bytes is an FD frame's, whatever the message says
        frame = (_pack_fd if msg.is_fd or size > _DATA else _pack_classic)(can_id, size, 0, 0, data)
        stamp = msg.timestamp
        sec = int(stamp)
        nsec = int((stamp - sec) * 1e9 + 0.5)
        stamp_ns = _pack_stamp(sec, nsec if nsec < _SECOND else _LAST_NS)
        return frame, [(_SOL_SOCKET, SO_TIMESTAMPNS, stamp_ns)], 0, None

    def send(self, frame: bytes, flags: int = 0) -> int:
        """A kernel frame through python-can's ``send``: ENOBUFS (an OSError, as the socket's)
        when the transmit queue was full, :class:`BusLost` when the interface failed."""
        can_id, length, _, _ = _unpack_head(frame)
        extended = can_id & CAN_EFF_FLAG != 0
        # Positional (timestamp, id, extended, remote, error, channel, dlc, data), python-can's
        # documented order: a quarter of a µs less per frame than by keyword.
        msg = _Message(0.0, can_id & (_EFF_MASK if extended else _SFF_MASK), extended, False, False, None,
                       None, frame[_HEAD:_HEAD + length])
        try:
            self.bus.send(msg)
        except can.CanOperationError as exc:
            if exc.error_code in TX_FULL or "buffer full" in str(exc):
                raise OSError(errno.ENOBUFS, str(exc)) from None
            raise BusLost(f"send failed: {exc}") from None
        except can.CanError as exc:
            raise BusLost(f"send failed: {exc}") from None
        return len(frame)

    def close(self) -> None:
        self.bus.shutdown()


Link = SocketLink | BusLink
#: Opens the link on a channel: receiving the frames the matches name (None: send only).
LinkOpener = Callable[[str, "Iterable[FrameMatch] | None"], Link]


def opener(config: DaemonConfig, *, compiled: bool) -> LinkOpener:
    """How the daemon opens its links: on SocketCAN its own raw socket; with another interface,
    with ``bus.options`` (python-can's keyword arguments, which only python-can's bus honours),
    or ``compiled`` off (the reference path, for comparison), python-can's bus."""

    def open_link(channel: str, matches: Iterable[FrameMatch] | None) -> Link:
        if config.interface == "socketcan" and compiled and not config.bus_options:
            return SocketLink(open_raw_socket(channel, () if matches is None else matches))
        options = dict(config.bus_options)
        if matches is not None:
            options["can_filters"] = receive_filters(matches)
            if config.interface == "socketcan":
                options.setdefault("fd", True)  # see CAN FD frames, to count and drop them
        return BusLink(can.Bus(interface=config.interface, channel=channel, **options))

    return open_link


class Sender:
    """The one way out, for every frame the daemon sends: a kernel frame onto the sensor's link
    (or the gateway's output link), never waiting. A full transmit queue drops the frame and
    counts it; any other failure is :class:`BusLost`. The generated handler does the same with
    the links' own ``send`` and :meth:`failed`."""

    def __init__(self, stats: Stats) -> None:
        self.stats = stats
        self.link: Link | None = None  # the sensor's bus (None: down)
        self.out: Link | None = None  # the gateway's output bus (None: none, or down)

    def send(self, frame: bytes, *, gateway: bool = False) -> None:
        link = self.out if gateway else self.link
        if link is None:
            return
        try:
            link.send(frame, MSG_DONTWAIT)
        except OSError as exc:
            self.failed(exc)

    def close(self) -> None:
        """Close both links (a failure to close is only logged: the link is gone either way)."""
        for what, link in (("the output bus", self.out), ("the bus", self.link)):
            if link is not None:
                try:
                    link.close()
                except (OSError, can.CanError) as exc:
                    log.debug("closing %s: %s", what, exc)
        self.link = self.out = None

    def failed(self, exc: OSError) -> None:
        if exc.errno in TX_FULL:
            self.stats.tx_dropped += 1
            return
        raise BusLost(f"send failed: {exc}") from None
