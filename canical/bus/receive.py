"""Every frame that is not the raw frame as expected: counted and dropped, or an input taken in.

The receive loop (:meth:`canical.bus.daemon.Daemon.serve`) hands the raw frame straight to its
handler when its head and size are the expected ones; everything else comes here, named by its
``can_id`` with SocketCAN's flag bits: error, remote, CAN FD, unknown id are counted and
dropped; a frame carrying inputs updates their values and times; a raw frame known by another
id (a J1939 group at another priority, destination or source) goes to the raw frame's handler.
"""

from __future__ import annotations

from can.interfaces.socketcan.constants import CAN_EFF_FLAG, CAN_ERR_FLAG, CAN_RTR_FLAG

from canical.bus.frame_handler import FrameLayout, InputFrame
from canical.bus.frame_state import FrameState
from canical.bus.socketcan_constants import FRAME_KEY

__all__ = ["Classifier"]


class Classifier:
    """Frames by key: the raw frame's, the input frames', J1939 groups beyond their exact ids."""

    def __init__(self, layout: FrameLayout, state: FrameState) -> None:
        self.state = state
        self.raw_key = layout.raw_key
        self.inputs: dict[int, InputFrame] = layout.input_handlers
        raw_match = layout.raw_match
        #: J1939 groups matched beyond their exact id: the raw frame's first, then the inputs'.
        self.groups = tuple(([] if raw_match is None or raw_match.exact else [(raw_match, layout.raw_key)])
                            + list(layout.masked_inputs))
        self.keep_frames = frozenset(o.source_key for o in layout.own_held)

    def frame(self, can_id: int, data: bytes | bytearray, stamp: float, fd: bool) -> bool:
        """One frame: True when it is a raw frame for the raw frame's handler; else counted, or
        its inputs taken in."""
        stats = self.state.stats
        if can_id & CAN_ERR_FLAG:
            stats.error_frames += 1
            return False
        key = can_id & FRAME_KEY
        handler = None if key == self.raw_key else self.inputs.get(key)
        if key != self.raw_key and handler is None:
            known = self._group_key(key)
            if known is None:
                stats.unknown_ids += 1
                return False
            handler, key = (None if known == self.raw_key else self.inputs[known]), known
        if can_id & CAN_RTR_FLAG:
            stats.remote_frames += 1
            return False
        if fd:
            stats.fd_frames += 1
            return False
        if handler is None:
            return True
        if len(data) != handler.length:
            stats.bad_length += 1
            return False
        signals = handler.decode(data)
        if key in self.keep_frames:
            self.state.held_frames[key] = bytes(data)
        values, times = self.state.values, self.state.times
        for name, at in handler.inputs_at:
            values[name] = signals[at]
            times[name] = stamp
        stats.inputs_in += 1
        return False

    def _group_key(self, key: int) -> int | None:
        """The key of the message a frame whose id is not a message's own belongs to: a J1939
        group at another priority, destination or source (None: none of the daemon's)."""
        if not key & CAN_EFF_FLAG or not self.groups:
            return None
        can_id = key & ~CAN_EFF_FLAG
        for match, known in self.groups:
            if match.matches(can_id, True):
                return known
        return None
