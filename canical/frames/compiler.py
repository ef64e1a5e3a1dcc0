"""Frame codecs compiled from the DBC at start: straight-line integer code per message.

Why: cantools decodes and encodes through dicts, bitstruct and a conversion object per
signal, 2–7 µs per frame; the daemon pays that for every frame. The layout never changes
while it runs, so each message's codec is generated once, as Python source with every
shift, mask, scale and offset written in as a constant, and compiled:

* decode: the payload as one integer (``int.from_bytes``), each signal ``(w >> shift) & mask``,
  two's complement for signed signals, then ``raw * scale + offset`` with cantools' own
  scale and offset objects (an integer scale stays an integer, as cantools returns it);
* encode: the inverse with cantools' rounding (``round`` of the unscaled value, the exact
  integer path for integer scales), the same ``OverflowError`` for a raw value outside the
  signal's bits, and the fields OR-ed into one integer.

The DBC stays the single source of truth: nothing here knows a layout, and the tests prove
each compiled codec equal to cantools on randomised payloads and values (sign, rounding,
edges, out of range). A layout the compiler does not handle (multiplexed, container, float
signals, a conversion it does not know) gets :class:`CantoolsCodec`, the same interface
over cantools, and :func:`codec_for` logs which and why.
"""

from __future__ import annotations

import logging
import math
import struct
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from operator import itemgetter
from typing import Any, Protocol

from cantools.database.can import Message
from cantools.database.conversion import (
    BaseConversion,
    IdentityConversion,
    LinearConversion,
    LinearIntegerConversion,
    NamedSignalConversion,
)

log = logging.getLogger("canical.frames.compiler")


class FrameCodec(Protocol):
    """Decode a payload to values in signal order, and encode values in that order."""

    names: tuple[str, ...]

    def decode(self, data: bytes | bytearray) -> tuple[Any, ...]: ...

    def encode(self, values: Sequence[Any]) -> bytes: ...


class NotCompilable(ValueError):
    """The message's layout is outside what :func:`compile_codec` generates code for."""


class CantoolsCodec:
    """The reference: cantools' own encode/decode behind the same interface."""

    __slots__ = ("_decode", "_encode", "_in_order", "names")

    def __init__(self, message: Message) -> None:
        self.names = tuple(s.name for s in message.signals)
        self._decode = message.decode
        self._encode = message.encode
        self._in_order = _in_order(self.names)

    def decode(self, data: bytes | bytearray) -> tuple[Any, ...]:
        values = self._decode(data, decode_choices=False)  # type: ignore[arg-type]  # cantools takes a bytearray too
        return self._in_order(values)

    def encode(self, values: Sequence[Any]) -> bytes:
        return self._encode(dict(zip(self.names, values, strict=True)), strict=False)


def _in_order(names: tuple[str, ...]) -> Callable[[Any], tuple[Any, ...]]:
    """Decoded values in signal order in one C call (a quarter of a µs less per frame than a
    generator); ``itemgetter`` of one name gives the value itself, of none is an error."""
    if len(names) > 1:
        return itemgetter(*names)
    if names:
        pick = itemgetter(names[0])
        return lambda values: (pick(values),)
    return lambda values: ()


class CompiledCodec:
    """A message's codec as generated code; ``source`` is kept for inspection and tests."""

    __slots__ = ("decode", "encode", "names", "source")

    def __init__(self, names: tuple[str, ...], source: str, namespace: dict[str, Any]) -> None:
        self.names = names
        self.source = source
        self.decode = namespace["decode"]
        self.encode = namespace["encode"]


def _why_not(message: Message) -> str | None:
    """Why this layout is not compiled (None: it is)."""
    if message.is_container:
        return "container frame"
    if message.is_multiplexed():
        return "multiplexed"
    if not message.signals:
        return "no signals"
    for sig in message.signals:
        conv = _numeric(sig.conversion)
        if conv.is_float:
            return f"signal {sig.name} is a float"
        if type(conv) not in (IdentityConversion, LinearIntegerConversion, LinearConversion):
            return f"signal {sig.name} has conversion {type(conv).__name__}"
        if sig.length < 1:
            return f"signal {sig.name} has no bits"
        end = sig.start + sig.length if sig.byte_order == "little_endian" else (
            _network_bit(sig.start) + sig.length)
        if end > 8 * message.length:
            return f"signal {sig.name} lies beyond the frame's {message.length} bytes"
    return None


def _numeric(conv: BaseConversion) -> BaseConversion:
    """The numeric conversion under a signal's value table (values are numbers here, never names)."""
    return conv._conversion if isinstance(conv, NamedSignalConversion) else conv


def _network_bit(sawtooth: int) -> int:
    """Big-endian start bit (DBC sawtooth numbering) as a bit index from the frame's first MSB."""
    return 8 * (sawtooth // 8) + (7 - sawtooth % 8)


def compile_codec(message: Message) -> CompiledCodec:
    """Generate and compile ``message``'s codec; :class:`NotCompilable` when the layout is not handled."""
    reason = _why_not(message)
    if reason is not None:
        raise NotCompilable(reason)
    nbytes = message.length
    names = tuple(s.name for s in message.signals)
    orders = {s.byte_order for s in message.signals}
    unpack = f"    ({', '.join(f'v{i}' for i in range(len(names)))},) = values"
    outs: list[str]
    dec = ["def decode_word(data):"]
    if "little_endian" in orders:
        dec.append("    le = from_bytes(data, 'little')")
    if "big_endian" in orders:
        dec.append("    be = from_bytes(data, 'big')")
    layout = _struct_layout(message) if orders == {"little_endian"} else None
    exact: list[str] = []  # cantools' semantics for any number
    ranges: list[str] = []  # checked after every value is converted, as cantools does
    rounded: list[str] = []  # the signals that need round() even for an integer (scaled ones)
    rounded_ranges: list[str] = []
    checks: list[str] = []  # signed fields, one check each
    unsigned: dict[int, list[str]] = {}  # unsigned fields by width: one check for all of a width
    fast_fields: dict[str, list[str]] = {"little_endian": [], "big_endian": []}  # integers as they are
    fields: dict[str, list[str]] = {"little_endian": [], "big_endian": []}
    outs = []
    exact_values: list[str] = []  # per signal, its raw integer as encode_exact has it (struct layout)
    fast_values: list[str] = []  # and as the fast encode has it
    for i, sig in enumerate(message.signals):
        n, order = sig.length, sig.byte_order
        mask = (1 << n) - 1
        shift = sig.start if order == "little_endian" else 8 * nbytes - (_network_bit(sig.start) + n)
        word = "le" if order == "little_endian" else "be"
        conv = _numeric(sig.conversion)
        # decode: the field's bits, two's complement, then cantools' raw * scale + offset
        bits = f"({word} >> {shift})" if shift else word
        dec.append(f"    r{i} = {bits} & {mask:#x}")
        if sig.is_signed:
            dec.append(f"    if r{i} & {1 << (n - 1):#x}: r{i} -= {1 << n:#x}")
        outs.append(_physical(conv, f"r{i}"))
        # encode: cantools' numeric_scaled_to_raw (round, exact integer path), range, field
        lines = _to_raw(conv, f"v{i}", f"r{i}")
        # in range ⇔ no bit above the field's (a signed range moved to 0…2ⁿ−1 first)
        bias = f" + {1 << (n - 1):#x}" if sig.is_signed else ""
        check = f"    if (r{i}{bias}) >> {n}: overflow({sig.name!r}, r{i})"
        exact += lines
        ranges.append(check)
        exact_values.append(f"r{i}")
        fast_values.append(f"v{i}" if isinstance(conv, IdentityConversion) else f"r{i}")
        part = f"(r{i} & {mask:#x})" if sig.is_signed else f"r{i}"
        fields[order].append(f"({part} << {shift})" if shift else part)
        if isinstance(conv, IdentityConversion):  # an int needs no rounding: skip round() per flag
            if sig.is_signed:
                checks.append(f"((v{i}{bias}) >> {n})")
            else:  # a negative or too wide value leaves a bit above n in the OR of them all
                unsigned.setdefault(n, []).append(f"v{i}")
            vpart = f"(v{i} & {mask:#x})" if sig.is_signed else f"v{i}"
            fast_fields[order].append(f"({vpart} << {shift})" if shift else vpart)
        else:
            rounded += lines
            rounded_ranges.append(check)
            fast_fields[order].append(f"({part} << {shift})" if shift else part)
    dec.append(f"    return ({', '.join(outs)},)")

    def packed(parts: dict[str, list[str]]) -> str:
        return _pack_word(parts, nbytes)

    if layout is None:
        pack_exact, pack_fast = packed(fields), packed(fast_fields)
        dec[0] = "def decode(data):"
    else:
        pack_exact = _pack_struct(layout, message, exact_values)
        pack_fast = _pack_struct(layout, message, fast_values)
        dec = [*_unpack_struct(layout, message, outs), "", "", *dec]

    exact = ["def encode_exact(values):", unpack, *exact, *ranges, f"    return {pack_exact}"]
    enc = ["def encode(values):"]
    checks += [f"(({' | '.join(names_)}) >> {n})" for n, names_ in unsigned.items()]
    if checks:
        # The common case, integers (or bools) in range, without a round() per signal; a float,
        # a negative or too wide value goes the exact way, which rounds, or raises as cantools does.
        slow = "return encode_exact(values)"
        enc += [unpack, "    try:", f"        if {' | '.join(checks)}:", f"            {slow}",
                "    except TypeError:", f"        {slow}"]
        enc += [*rounded, *rounded_ranges, f"    return {pack_fast}"]
    else:
        enc = ["encode = encode_exact"]
    source = "\n".join(dec) + "\n\n\n" + "\n".join(exact) + "\n\n\n" + "\n".join(enc) + "\n"
    namespace: dict[str, Any] = {"from_bytes": int.from_bytes, "overflow": _overflow,
                                 "struct_error": struct.error}
    if layout is not None:
        namespace["unpack_from"] = layout.struct.unpack_from
        namespace["pack"] = layout.struct.pack
    exec(compile(source, f"<codec {message.name}>", "exec"), namespace)
    return CompiledCodec(names, source, namespace)


def _physical(conv: BaseConversion, r: str) -> str:
    """cantools' physical value of the raw integer ``r``: ``r * scale + offset``, as it types it."""
    if isinstance(conv, IdentityConversion):
        return r
    if conv.offset == 0 and conv.scale > 0:  # + 0 changes nothing (r * scale is never -0.0)
        return f"{r} * {conv.scale!r}"
    return f"{r} * {conv.scale!r} + {conv.offset!r}"


def decode_lines(message: Message, data: str, outs: Sequence[str | None],
                 tag: str = "dec_") -> tuple[list[str], dict[str, Any]]:
    """Decoding ``message`` written into a caller's generated function: statements (one level
    of indentation) setting the local names ``outs`` (signal order) to what ``decode`` returns,
    and the names they need; a signal whose name is None is not decoded (the caller does not
    use it). ``data`` is the payload's expression; the caller promises it is
    exactly the message's length (the short-payload path of ``decode`` is not written).
    Temporaries start with ``tag``. :class:`NotCompilable` as :func:`compile_codec`.
    """
    nbytes, layout = _compilable_layout(message)
    namespace: dict[str, Any] = {"from_bytes": int.from_bytes}
    lines: list[str] = []
    raws: list[str] = []
    convs = [_numeric(sig.conversion) for sig in message.signals]
    if layout is not None:
        # A whole field that is an unscaled signal is unpacked straight into its output.
        targets = [(outs[j] or f"{tag}f{k}") if j >= 0 and isinstance(convs[j], IdentityConversion)
                   else f"{tag}f{k}"
                   for k, (j, _, _) in enumerate(layout.fields)]
        namespace[f"{tag}unpack"] = layout.struct.unpack
        lines.append(f"    {', '.join(targets)}, = {tag}unpack({data})")
        for k, (j, _, n) in enumerate(layout.fields):
            if j < 0 and 8 * n not in STRUCT_CODES:
                lines.append(f"    {targets[k]} = from_bytes({targets[k]}, 'little')")
        for i, sig in enumerate(message.signals):
            k = layout.owner[i]
            j, first, _ = layout.fields[k]
            if j == i or outs[i] is None:
                raws.append(targets[k])
                continue
            r = _raw_name(convs[i], outs[i], f"{tag}r{i}")
            shift, mask = sig.start - 8 * first, (1 << sig.length) - 1
            lines.append(f"    {r} = {f'({targets[k]} >> {shift})' if shift else targets[k]} & {mask:#x}")
            if sig.is_signed:
                lines.append(f"    if {r} & {1 << (sig.length - 1):#x}: {r} -= {1 << sig.length:#x}")
            raws.append(r)
    else:
        for order, word in (("little_endian", "le"), ("big_endian", "be")):
            if any(s.byte_order == order for s in message.signals):
                lines.append(f"    {tag}{word} = from_bytes({data}, '{order.split('_')[0]}')")
        for i, sig in enumerate(message.signals):
            r = _raw_name(convs[i], outs[i], f"{tag}r{i}")
            raws.append(r)
            if outs[i] is None:
                continue
            n = sig.length
            shift = (sig.start if sig.byte_order == "little_endian"
                     else 8 * nbytes - (_network_bit(sig.start) + n))
            word = f"{tag}le" if sig.byte_order == "little_endian" else f"{tag}be"
            lines.append(f"    {r} = {f'({word} >> {shift})' if shift else word} & {(1 << n) - 1:#x}")
            if sig.is_signed:
                lines.append(f"    if {r} & {1 << (n - 1):#x}: {r} -= {1 << n:#x}")
    for out, raw, conv in zip(outs, raws, convs, strict=True):
        if out is not None and out != raw:
            lines.append(f"    {out} = {_physical(conv, raw)}")
    return lines, namespace


def _raw_name(conv: BaseConversion, out: str | None, temporary: str) -> str:
    """Where a decoded field's integer goes: straight into its output when unscaled."""
    return out if out is not None and isinstance(conv, IdentityConversion) else temporary


def _to_raw(conv: BaseConversion, v: str, r: str, tmp: str = "") -> list[str]:
    """Statements setting ``r`` to cantools' raw integer of the value ``v`` (its
    ``numeric_scaled_to_raw``: ``round``, the exact integer path for integer scales)."""
    off = f" - {conv.offset!r}" if not isinstance(conv, IdentityConversion) and conv.offset != 0 else ""
    if isinstance(conv, IdentityConversion):
        return [f"    {r} = round({v})"]
    if isinstance(conv, LinearIntegerConversion) and conv.scale != 1:
        return [f"    {tmp}x = {v}{off}", f"    {tmp}q, {tmp}rem = divmod({tmp}x, {conv.scale!r})",
                f"    {r} = round({tmp}q if {tmp}rem == 0 else {tmp}x / {conv.scale!r})"]
    if isinstance(conv, LinearIntegerConversion):
        return [f"    {r} = round({v}{off})"]
    return [f"    {r} = round(({v}{off}) / {conv.scale!r})"]


def _fits(conv: BaseConversion, span: tuple[float, float], bias: int, n: int) -> bool:
    """Whether every value in ``span`` gives a raw integer the signal's ``n`` bits hold: the
    statements of :func:`_to_raw`, run on both ends (rounding is monotonic in the value)."""
    namespace: dict[str, Any] = {}
    source = "\n".join(["def raw(v):", *_to_raw(conv, "(v)", "r"), "    return r"]) + "\n"
    exec(compile(source, "<raw of an end>", "exec"), namespace)
    try:
        return all(math.isfinite(end) and not (namespace["raw"](end) + bias) >> n for end in span)
    except (OverflowError, ValueError):  # an end whose raw value is not even an integer
        return False


def _pack_word(parts: dict[str, list[str]], nbytes: int) -> str:
    """The payload from the OR of shifted fields, per byte order (the integer form)."""
    le = " | ".join(parts["little_endian"]) or "0"
    be = " | ".join(parts["big_endian"])
    if parts["little_endian"] and be:
        return (f"(({le}) | from_bytes(({be}).to_bytes({nbytes}, 'big'), 'little'))"
                f".to_bytes({nbytes}, 'little')")
    return f"({be}).to_bytes({nbytes}, 'big')" if be else f"({le}).to_bytes({nbytes}, 'little')"


def encode_lines(message: Message, values: Sequence[str], bounds: Sequence[int | None],
                 tag: str = "enc_", spans: Sequence[tuple[float, float] | None] | None = None,
                 ) -> tuple[list[str], dict[str, Any], str]:
    """Encoding ``message`` written into a caller's generated function: statements (one level
    of indentation), the names they need, and the payload's expression.

    ``values`` are the signals' value expressions in signal order. ``bounds[i]``, where not
    None, is the caller's promise that value ``i`` is an int (or bool) from 0 to that bound:
    an unscaled signal that holds it is packed as it is, with no rounding and no check (the
    flags, counters and tags of a frame the caller builds). Every other value goes the exact
    way of ``encode`` (round, range check, ``OverflowError`` as cantools). A value ``False``
    or ``0`` adds nothing and is left out. ``spans[i]``, where given, is the caller's promise
    that value ``i`` is a finite number from ``lo`` to ``hi`` (a rate it has saturated): it is
    rounded as always, and its range check is left out when both ends' raw values fit, since
    the rounding is monotonic in the value and so every value between fits too.
    :class:`NotCompilable` as :func:`compile_codec`.
    """
    nbytes, layout = _compilable_layout(message)
    lines: list[str] = []
    checks: list[str] = []
    raws: list[str] = []
    fields: dict[str, list[str]] = {"little_endian": [], "big_endian": []}
    for i, sig in enumerate(message.signals):
        n, order, conv = sig.length, sig.byte_order, _numeric(sig.conversion)
        top = 1 << (n - 1) if sig.is_signed else 1 << n
        bound = bounds[i]
        if isinstance(conv, IdentityConversion) and bound is not None and 0 <= bound < top:
            r = values[i]
        else:
            r = f"{tag}r{i}"
            lines += _to_raw(conv, f"({values[i]})", r, tmp=tag)
            bias = 1 << (n - 1) if sig.is_signed else 0
            span = spans[i] if spans is not None else None
            if span is None or not _fits(conv, span, bias, n):
                checks.append(f"    if ({r} + {bias:#x}) >> {n}: {tag}overflow({sig.name!r}, {r})" if bias
                              else f"    if {r} >> {n}: {tag}overflow({sig.name!r}, {r})")
        raws.append(r)
        if r in ("False", "0"):
            continue
        shift = sig.start if order == "little_endian" else 8 * nbytes - (_network_bit(sig.start) + n)
        part = f"({r} & {(1 << n) - 1:#x})" if sig.is_signed else r
        fields[order].append(f"({part} << {shift})" if shift else part)
    namespace: dict[str, Any] = {f"{tag}overflow": _overflow, "from_bytes": int.from_bytes}
    if layout is None:
        return [*lines, *checks], namespace, _pack_word(fields, nbytes)
    namespace[f"{tag}pack"] = layout.struct.pack
    return [*lines, *checks], namespace, _pack_struct(layout, message, raws, pack=f"{tag}pack")


#: struct codes of byte-aligned little-endian integers, by width in bits: (unsigned, signed).
STRUCT_CODES = {8: ("B", "b"), 16: ("H", "h"), 32: ("I", "i"), 64: ("Q", "q")}


@dataclass(frozen=True)
class StructLayout:
    """A little-endian frame as ``struct`` fields: whole signals that fill aligned bytes of a
    standard width, and runs of the other bytes, each one unsigned integer whose bits hold the
    signals inside it (a run of a width struct lacks is read as bytes, then ``int.from_bytes``)."""

    struct: struct.Struct
    #: per field: (the signal that fills it, or -1 for a run; first byte; length in bytes)
    fields: tuple[tuple[int, int, int], ...]
    owner: tuple[int, ...]  # per signal: its field


def _compilable_layout(message: Message) -> tuple[int, StructLayout | None]:
    """The frame's length and, for an all little-endian frame, its ``struct`` layout.

    :class:`NotCompilable` when the compiler does not handle the message at all.
    """
    reason = _why_not(message)
    if reason is not None:
        raise NotCompilable(reason)
    orders = {s.byte_order for s in message.signals}
    return message.length, _struct_layout(message) if orders == {"little_endian"} else None


def _struct_layout(message: Message) -> StructLayout | None:
    """The frame as ``struct`` fields (see :class:`StructLayout`), for little-endian signals."""
    nbytes = message.length
    covers = [(s.start // 8, (s.start + s.length - 1) // 8) for s in message.signals]
    whole = []
    for i, sig in enumerate(message.signals):
        first, last = covers[i]
        aligned = sig.start % 8 == 0 and sig.length in STRUCT_CODES
        alone = all(j == i or b < first or a > last for j, (a, b) in enumerate(covers))
        if aligned and alone:
            whole.append(i)
    if not whole:
        return None
    starts = {covers[i][0]: i for i in whole}
    fields: list[tuple[int, int, int]] = []
    fmt = "<"
    byte = 0
    while byte < nbytes:
        if byte in starts:
            i = starts[byte]
            width = message.signals[i].length // 8
            fields.append((i, byte, width))
            fmt += STRUCT_CODES[8 * width][message.signals[i].is_signed]
            byte += width
            continue
        end = byte
        while end < nbytes and end not in starts:
            end += 1
        fields.append((-1, byte, end - byte))
        fmt += STRUCT_CODES[8 * (end - byte)][0] if 8 * (end - byte) in STRUCT_CODES else f"{end - byte}s"
        byte = end
    owner = tuple(next(k for k, (j, a, n) in enumerate(fields)
                       if j == i or (j < 0 and a <= lo and hi < a + n)) for i, (lo, hi) in enumerate(covers))
    return StructLayout(struct.Struct(fmt), tuple(fields), owner)


def _unpack_struct(layout: StructLayout, message: Message, outs: list[str]) -> list[str]:
    """``decode`` on the struct layout: one ``unpack_from``, each signal from its field; a
    payload shorter than the frame goes to ``decode_word`` (the integer form, as cantools)."""
    names = [f"f{k}" for k in range(len(layout.fields))]
    lines = ["def decode(data):", "    try:", f"        {', '.join(names)}, = unpack_from(data)",
             "    except struct_error:", "        return decode_word(data)"]
    for k, (j, _, n) in enumerate(layout.fields):
        if j < 0 and 8 * n not in STRUCT_CODES:
            lines.append(f"    f{k} = from_bytes(f{k}, 'little')")
    for i, sig in enumerate(message.signals):
        k = layout.owner[i]
        j, first, _ = layout.fields[k]
        if j == i:
            lines.append(f"    r{i} = f{k}")
            continue
        shift, mask = sig.start - 8 * first, (1 << sig.length) - 1
        lines.append(f"    r{i} = {f'(f{k} >> {shift})' if shift else f'f{k}'} & {mask:#x}")
        if sig.is_signed:
            lines.append(f"    if r{i} & {1 << (sig.length - 1):#x}: r{i} -= {1 << sig.length:#x}")
    lines.append(f"    return ({', '.join(outs)},)")
    return lines


def _pack_struct(layout: StructLayout, message: Message, values: list[str], pack: str = "pack") -> str:
    """The ``pack`` call for raw integers ``values`` (in range: checked before) on the layout."""
    args = []
    for k, (j, first, n) in enumerate(layout.fields):
        if j >= 0:
            args.append(values[j])
            continue
        parts = []
        for i, sig in enumerate(message.signals):
            if layout.owner[i] != k or values[i] in ("False", "0"):
                continue
            part = f"({values[i]} & {(1 << sig.length) - 1:#x})" if sig.is_signed else values[i]
            shift = sig.start - 8 * first
            parts.append(f"({part} << {shift})" if shift else part)
        word = " | ".join(parts) or "0"
        args.append(word if 8 * n in STRUCT_CODES else f"({word}).to_bytes({n}, 'little')")
    return f"{pack}({', '.join(args)})"


def _overflow(name: str, raw: int) -> None:
    """What cantools raises for a raw value its bits cannot hold."""
    raise OverflowError(f"signal {name}: raw value {raw} out of range")


def codec_for(message: Message, *, compiled: bool = True) -> FrameCodec:
    """The compiled codec of ``message``, or cantools' (logged, with the reason) when not compilable."""
    if not compiled:
        return CantoolsCodec(message)
    try:
        return compile_codec(message)
    except NotCompilable as exc:
        log.info("frame %s: layout not compiled (%s); using cantools", message.name, exc)
        return CantoolsCodec(message)
