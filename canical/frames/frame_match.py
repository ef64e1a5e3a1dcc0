"""Which received frames are a DBC message: its exact id, or for J1939 its parameter group.

Why: a J1939 node's 29-bit id is priority, parameter group number (PGN) and source address. A
vehicle may send a message at another priority than the DBC's, a PDU1 group carries its
destination in the id, and an IMU's source address is set when it is fitted (address claim),
so the DBC's id is only one of the ids the message arrives with. A message the DBC marks as J1939
(cantools' ``protocol == "j1939"``) is therefore matched by its PGN, priority and destination
ignored, and by the DBC's source address, a configured one, or any. Everything else is matched
by its exact id, as before. The daemon, the CAN log reader and ``record`` match with the same
:class:`FrameMatcher`, so the frames a log gives ``calibrate`` are the frames ``serve`` corrects.
"""

from __future__ import annotations

import re
from collections.abc import Iterable
from dataclasses import dataclass
from typing import Generic, Literal, TypeVar

from cantools.database.can import Message

__all__ = ["ANY_SOURCE", "FrameMatch", "FrameMatcher", "J1939Source", "frame_match", "parse_j1939_source"]

ANY_SOURCE: Literal["any"] = "any"
#: Which J1939 source address a message is matched with: the DBC's (None), a given one, or any.
J1939Source = int | Literal["any"] | None

ID_29_BITS = 0x1FFF_FFFF
PRIORITY_BITS = 0x7 << 26
PDU_SPECIFIC_BITS = 0xFF << 8
SOURCE_BITS = 0xFF
PDU2_FROM = 240  # PDU format 240..255: the PDU-specific byte is part of the PGN (group extension)

T = TypeVar("T")
#: An address written as text: decimal or 0x hex, nothing Python's int() also takes ("1_0", "0b1").
_ADDRESS_TEXT = re.compile(r"0[xX][0-9a-fA-F]{1,2}|[0-9]{1,3}")


@dataclass(frozen=True)
class FrameMatch:
    """A message's frames: an id ``id & mask == frame_id`` (extended or standard as ``extended``)."""

    frame_id: int
    extended: bool
    mask: int
    #: The id it usually arrives with: the DBC's, with a configured source address in it. The
    #: daemon's fast path compares whole frame heads with it before matching by mask.
    usual_id: int = -1

    def __post_init__(self) -> None:
        if self.usual_id < 0:
            object.__setattr__(self, "usual_id", self.frame_id)

    @property
    def exact(self) -> bool:
        return self.mask == (ID_29_BITS if self.extended else 0x7FF)

    def matches(self, can_id: int, extended: bool) -> bool:
        return extended == self.extended and can_id & self.mask == self.frame_id

    def describe(self) -> str:
        if self.exact:
            return f"id 0x{self.frame_id:x}"
        pgn = (self.frame_id >> 8) & 0x3FFFF
        source = "any source" if not self.mask & SOURCE_BITS else f"source 0x{self.frame_id & 0xFF:02x}"
        return f"J1939 PGN 0x{pgn:05x} ({pgn}), {source}"


def frame_match(message: Message, source: J1939Source = None) -> FrameMatch:
    """How ``message``'s frames are recognised (see the module's doc)."""
    frame_id, extended = message.frame_id, bool(message.is_extended_frame)
    if not (extended and message.protocol == "j1939"):
        return FrameMatch(frame_id, extended, ID_29_BITS if extended else 0x7FF)
    mask = ID_29_BITS & ~PRIORITY_BITS
    if (frame_id >> 16) & 0xFF < PDU2_FROM:  # PDU1: the PDU-specific byte is a destination
        mask &= ~PDU_SPECIFIC_BITS
    if source == ANY_SOURCE:
        mask &= ~SOURCE_BITS
    elif source is not None:
        frame_id = (frame_id & ~SOURCE_BITS) | source
    return FrameMatch(frame_id & mask, True, mask, usual_id=frame_id)


def parse_j1939_source(value: object, where: str) -> J1939Source:
    """``any``, or a source address 0..253 (254 is null, 255 global): ValueError naming ``where``."""
    if value is None or value == ANY_SOURCE:
        return value
    if isinstance(value, str):
        if not _ADDRESS_TEXT.fullmatch(value.strip()):  # int(..., 0) reads "1_0" as 10
            raise ValueError(f"{where}: must be 'any' or a source address 0..253, got {value!r}")
        value = int(value.strip(), 0)
    if isinstance(value, bool) or not isinstance(value, int) or not 0 <= value <= 253:
        raise ValueError(f"{where}: must be 'any' or a source address 0..253, got {value!r}")
    return value


class FrameMatcher(Generic[T]):
    """Values by message, looked up by a received frame's id: exact ids by one dict lookup, J1939
    groups (few) by their masks when that misses."""

    def __init__(self, entries: Iterable[tuple[FrameMatch, T]]) -> None:
        self.exact: dict[tuple[int, bool], T] = {}
        self.masked: list[tuple[FrameMatch, T]] = []
        for match, value in entries:
            if match.exact:
                self.exact.setdefault((match.frame_id, match.extended), value)
            else:
                self.masked.append((match, value))

    def get(self, can_id: int, extended: bool) -> T | None:
        value = self.exact.get((can_id, extended))
        if value is not None or not extended:
            return value
        for match, candidate in self.masked:
            if can_id & match.mask == match.frame_id:
                return candidate
        return None
