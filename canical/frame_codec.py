"""Frames as the DBC describes them: decode the raw IMU frame, encode corrected and status frames.

The DBC is the single source of truth for layouts: nothing here knows a byte offset.
cantools compiles each message's codec when the database loads; what is left for the
per-frame path is prepared once in the constructors below (message objects, the signal
ranges rates are saturated to, a reusable dict of output values), so encoding a frame is
one clamp per rate and one ``encode`` call.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path
from typing import Any

import cantools
from cantools.database.can import Database, Message

from canical.errors import CanicalError


def load_dbc(path: str | os.PathLike[str]) -> Database:
    """Load a DBC file; a missing or malformed one is one :class:`CanicalError` line."""
    name = str(path)
    if not Path(path).is_file():
        raise CanicalError(f"{name}: DBC file not found")
    try:
        db = cantools.database.load_file(name, database_format="dbc", strict=True)
    except Exception as exc:  # cantools raises many types for a bad file
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CanicalError(f"{name}: not a valid DBC file ({first})") from None
    return db  # type: ignore[return-value]


def signal_range(message: Message, name: str) -> tuple[float, float]:
    """The physical range a signal can carry: its DBC min/max, within what its bits can encode."""
    sig = message.get_signal_by_name(name)
    if sig.is_signed:
        lo_raw, hi_raw = -(1 << (sig.length - 1)), (1 << (sig.length - 1)) - 1
    else:
        lo_raw, hi_raw = 0, (1 << sig.length) - 1
    ends = (lo_raw * sig.scale + sig.offset, hi_raw * sig.scale + sig.offset)
    lo, hi = min(ends), max(ends)
    if sig.minimum is not None:
        lo = max(lo, float(sig.minimum))
    if sig.maximum is not None:
        hi = min(hi, float(sig.maximum))
    return float(lo), float(hi)


class RawDecoder:
    """Decode one message (the IMU's raw frame, or a frame carrying inputs) to physical values."""

    __slots__ = ("_decode", "frame_id", "is_extended", "length", "name")

    def __init__(self, message: Message) -> None:
        self.name = message.name
        self.frame_id = message.frame_id
        self.is_extended = message.is_extended_frame
        self.length = message.length
        self._decode = message.decode

    def decode(self, data: bytes | bytearray) -> dict[str, Any]:
        """Signal name → physical value; numeric, never a choice string."""
        return self._decode(data, decode_choices=False)  # type: ignore[return-value]


class RateEncoder:
    """Encode the corrected frame: three rates saturated to their signal range, flags, tag, counter."""

    __slots__ = ("_encode", "_values", "flag_names", "frame_id", "is_extended", "length", "limits",
                 "name", "rate_names")

    def __init__(self, message: Message, axes: Iterable[str] = ("x", "y", "z")) -> None:
        self.name = message.name
        self.frame_id = message.frame_id
        self.is_extended = message.is_extended_frame
        self.length = message.length
        self._encode = message.encode
        self.rate_names = tuple(f"Rate{a.upper()}" for a in axes)
        self.flag_names = tuple((f"OutOfSpan{a.upper()}", f"Uncalibrated{a.upper()}") for a in axes)
        self.limits = tuple(signal_range(message, n) for n in self.rate_names)
        self._values: dict[str, float | int] = {s.name: 0 for s in message.signals}

    def encode(
        self,
        rates: Iterable[float],
        out_of_span: Iterable[bool],
        uncalibrated: Iterable[bool],
        stale: bool,
        counter_gap: bool,
        set_tag: int,
        counter: int,
    ) -> bytes:
        """One frame's payload. A rate beyond the signal's range is sent at the range's end."""
        v = self._values
        for name, (lo, hi), rate, (oos_name, unc_name), oos, unc in zip(
            self.rate_names, self.limits, rates, self.flag_names, out_of_span, uncalibrated, strict=True
        ):
            v[name] = lo if rate < lo else hi if rate > hi else rate
            v[oos_name] = 1 if oos else 0
            v[unc_name] = 1 if unc else 0
        v["Stale"] = 1 if stale else 0
        v["CounterGap"] = 1 if counter_gap else 0
        v["SetTag"] = set_tag
        v["Counter"] = counter
        return self._encode(v, strict=False)


class StatusEncoder:
    """Encode pages of the multiplexed status frame; counters wrap to their signal width or saturate."""

    __slots__ = ("_message", "_pages", "_widths", "frame_id", "is_extended", "length", "name")

    def __init__(self, message: Message) -> None:
        self._message = message
        self.name = message.name
        self.frame_id = message.frame_id
        self.is_extended = message.is_extended_frame
        self.length = message.length
        self._widths = {s.name: s.length for s in message.signals}
        self._pages: dict[int, tuple[str, ...]] = {}
        for sig in message.signals:
            for page in sig.multiplexer_ids or ():
                self._pages[page] = (*self._pages.get(page, ()), sig.name)

    @property
    def pages(self) -> tuple[int, ...]:
        return tuple(sorted(self._pages))

    def encode(self, page: int, values: dict[str, int], *, saturate: bool = False) -> bytes:
        """Page ``page``: its signals from ``values`` (0 when absent), counters modulo their width,
        or held at their maximum with ``saturate`` (fault counts, where a wrap would read as few)."""
        data: dict[str, int] = {"Page": page}
        for name in self._pages.get(page, ()):
            top = (1 << self._widths[name]) - 1
            value = int(values.get(name, 0))
            data[name] = min(value, top) if saturate else value & top
        return self._message.encode(data, strict=False)
