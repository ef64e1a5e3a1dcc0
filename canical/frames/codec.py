"""Frames as the DBC describes them: decode the raw IMU frame, encode corrected and status frames.

The DBC is the single source of truth for layouts: nothing here knows a byte offset.
Each per-frame codec is generated from the DBC at start (:mod:`canical.frames.compiler`,
cantools where a layout is not compiled); what else the per-frame path needs is prepared
once in the constructors below (the signal ranges rates are saturated to, the order of the
values), so encoding a frame is one clamp per rate and one ``encode`` call.
"""

from __future__ import annotations

from collections.abc import Iterable
from typing import Any

from cantools.database.can import Message

from canical.frames.compiler import codec_for
from canical.frames.dbc_files import load_dbc

__all__ = ["RateEncoder", "RawDecoder", "StatusEncoder", "load_dbc", "signal_range"]


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
    """Decode one message (the IMU's raw frame, or a frame carrying inputs) to physical values.

    ``values`` is the per-frame form: a tuple in signal order (``index`` maps names to
    positions), from the codec compiled at start (:mod:`canical.frames.compiler`), or from
    cantools where the layout is not compiled or ``compiled`` is False.
    """

    __slots__ = ("_decode", "frame_id", "index", "is_extended", "length", "name", "values")

    def __init__(self, message: Message, *, compiled: bool = True) -> None:
        self.name = message.name
        self.frame_id = message.frame_id
        self.is_extended = message.is_extended_frame
        self.length = message.length
        self._decode = message.decode
        codec = codec_for(message, compiled=compiled)
        self.values = codec.decode
        self.index = {name: i for i, name in enumerate(codec.names)}

    def decode(self, data: bytes | bytearray) -> dict[str, Any]:
        """Signal name → physical value; numeric, never a choice string."""
        return self._decode(data, decode_choices=False)  # type: ignore[arg-type, return-value]


class RateEncoder:
    """Encode the corrected frame: three rates saturated to their signal range, flags, tag, counter."""

    __slots__ = ("_encode", "_order", "encode_in_order", "flag_names", "frame_id", "is_extended", "length",
                 "limits", "name", "rate_names")

    def __init__(self, message: Message, axes: Iterable[str] = ("x", "y", "z"), *,
                 compiled: bool = True) -> None:
        self.name = message.name
        self.frame_id = message.frame_id
        self.is_extended = message.is_extended_frame
        self.length = message.length
        self.rate_names = tuple(f"Rate{a.upper()}" for a in axes)
        self.flag_names = tuple((f"OutOfSpan{a.upper()}", f"Uncalibrated{a.upper()}") for a in axes)
        # A rate frame without an axis's signal (a single-axis sensor's): that axis is never sent.
        names = {sig.name for sig in message.signals}
        self.limits = tuple(signal_range(message, n) if n in names else (0.0, 0.0) for n in self.rate_names)
        codec = codec_for(message, compiled=compiled)
        self._encode = codec.encode
        # The arguments in one canonical order; each signal's position in it (None: always 0).
        canonical = [*self.rate_names, *(f[0] for f in self.flag_names), *(f[1] for f in self.flag_names),
                     "Stale", "CounterGap", "SetTag", "Counter"]
        order = tuple(canonical.index(n) if n in canonical else None for n in codec.names)
        self._order = None if order == tuple(range(len(canonical))) else order  # None: as it comes
        #: The codec's encode, when it takes :meth:`encode_xyz`'s arguments as they are (rates
        #: saturated by the caller); None when the frame's signals come in another order.
        self.encode_in_order = codec.encode if self._order is None and len(self.limits) == 3 else None

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
        args = [lo if r < lo else hi if r > hi else r
                for r, (lo, hi) in zip(rates, self.limits, strict=True)]
        args += out_of_span
        args += uncalibrated
        args += (stale, counter_gap, set_tag, counter)
        order = self._order
        if order is not None:
            args = [0 if i is None else args[i] for i in order]
        return self._encode(args)

    def encode_xyz(self, rx: float, ry: float, rz: float, ox: bool, oy: bool, oz: bool, ux: bool, uy: bool,
                   uz: bool, stale: bool, counter_gap: bool, set_tag: int, counter: int) -> bytes:
        """:meth:`encode` for the three axes with the values as arguments: the per-frame form."""
        if self._order is not None or len(self.limits) != 3:
            return self.encode((rx, ry, rz), (ox, oy, oz), (ux, uy, uz), stale, counter_gap, set_tag, counter)
        (lx, hx), (ly, hy), (lz, hz) = self.limits
        return self._encode((lx if rx < lx else hx if rx > hx else rx,
                             ly if ry < ly else hy if ry > hy else ry,
                             lz if rz < lz else hz if rz > hz else rz,
                             ox, oy, oz, ux, uy, uz, stale, counter_gap, set_tag, counter))


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

    def encode_physical(self, page: int, values: dict[str, float]) -> bytes:
        """Page ``page`` from values in the signals' units (scaled, signed), each clamped to its range."""
        data: dict[str, float] = {"Page": page}
        for name in self._pages.get(page, ()):
            sig = self._message.get_signal_by_name(name)
            value = float(values.get(name, 0.0))
            lo = float(sig.minimum) if sig.minimum is not None else value
            hi = float(sig.maximum) if sig.maximum is not None else value
            data[name] = lo if value < lo else hi if value > hi else value
        return self._message.encode(data, strict=False)
