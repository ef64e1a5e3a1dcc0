"""Compiled frame codecs against cantools: randomised layouts, payloads and values must agree exactly.

Layouts are written as DBC text and loaded by cantools, so scales and offsets come out as the
parser makes them (an integer scale stays an integer). Values cover the edges of each signal's
bits, one beyond, halves (rounding), signs, bools, NaN and infinities: the compiled encoder
returns the same bytes, or raises the same exception type, as cantools.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import cantools
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from canical.frames.compiler import (
    CantoolsCodec,
    CompiledCodec,
    codec_for,
    compile_codec,
    decode_lines,
    encode_lines,
)

DBC = Path(__file__).resolve().parents[2] / "dbc" / "canical.dbc"
SCALES = (1, 2, 3, 10, -1, 0.1, 0.01, 0.001, 0.5, 0.25, 0.125, -0.5, 1e-4, 0.03125, 7.5)
OFFSETS = (0, 1, -1, -50, 100, 0.5, -0.25, -40.5, 1000.125, 3)


def same(a: object, b: object) -> bool:
    """Equal with the same type, and for floats the same sign of zero (bit-for-bit outputs)."""
    if type(a) is not type(b):
        return False
    if isinstance(a, float):
        return a == b and math.copysign(1.0, a) == math.copysign(1.0, b)  # type: ignore[arg-type]
    return a == b


def bits_of(order: str, start: int, length: int) -> set[tuple[int, int]]:
    """Physical (byte, bit) cells a signal covers."""
    if order == "le":
        return {((start + k) // 8, (start + k) % 8) for k in range(length)}
    network = 8 * (start // 8) + (7 - start % 8)  # MSB of a Motorola signal
    return {((network + k) // 8, 7 - (network + k) % 8) for k in range(length)}


@st.composite
def layouts(draw) -> str:
    """DBC text of one message with non-overlapping signals of any order, sign, scale, offset."""
    nbytes = draw(st.sampled_from((1, 2, 4, 6, 7, 8, 8, 8, 12, 16, 64)))
    used: set[tuple[int, int]] = set()
    lines = []
    # Little-endian frames (read through struct) as often as mixed ones, and signals that fill
    # whole aligned bytes of a struct width (8, 16, 32, 64 bits) among the others.
    orders = draw(st.sampled_from((("le", "be"), ("le",))))
    for i in range(draw(st.integers(1, 12))):
        order = draw(st.sampled_from(orders))
        aligned = order == "le" and draw(st.booleans())
        widths = [w for w in (8, 16, 32, 64) if w <= 8 * nbytes]
        length = draw(st.sampled_from(widths)) if aligned else draw(st.integers(1, min(64, 8 * nbytes)))
        if aligned:
            start = 8 * draw(st.integers(0, nbytes - length // 8))
        elif order == "le":
            start = draw(st.integers(0, 8 * nbytes - length))
        else:
            network = draw(st.integers(0, 8 * nbytes - length))
            start = 8 * (network // 8) + (7 - network % 8)  # DBC numbers Motorola bits sawtooth
        cells = bits_of(order, start, length)
        if cells & used:
            continue
        used |= cells
        signed = draw(st.booleans()) and length > 1
        scale, offset = draw(st.sampled_from(SCALES)), draw(st.sampled_from(OFFSETS))
        lines.append(f" SG_ S{i} : {start}|{length}@{1 if order == 'le' else 0}{'-' if signed else '+'} "
                     f"({scale!r},{offset!r}) [0|0] \"\" Vector__XXX")
    return (f'VERSION ""\n\nNS_ :\n\nBS_:\n\nBU_: A\n\nBO_ 100 M: {nbytes} A\n' + "\n".join(lines) + "\n")


def message_of(text: str):
    return cantools.database.load_string(text, database_format="dbc", strict=False).messages[0]


def values_for(draw, message) -> list:
    out = []
    for sig in message.signals:
        n = sig.length
        lo, hi = (-(1 << (n - 1)), (1 << (n - 1)) - 1) if sig.is_signed else (0, (1 << n) - 1)
        raw = draw(st.one_of(st.sampled_from((lo, hi, lo - 1, hi + 1, 0, 1, -1)), st.integers(lo, hi)))
        conv = sig.conversion
        kind = draw(st.sampled_from(("physical", "half", "int", "bool", "odd")))
        if kind == "physical":
            value = raw * conv.scale + conv.offset
        elif kind == "half":  # exactly between two raw values: rounding (to even) decides
            value = (raw + 0.5) * conv.scale + conv.offset
        elif kind == "int":
            value = int(raw * conv.scale + conv.offset) if isinstance(conv.scale, int) else raw
        elif kind == "bool":
            value = draw(st.booleans())
        else:
            value = draw(st.one_of(st.floats(allow_nan=True, allow_infinity=True),
                                   st.integers(-(1 << 70), 1 << 70)))
        out.append(value)
    return out


def encode_both(compiled: CompiledCodec, reference: CantoolsCodec, values: list) -> None:
    try:
        expected = reference.encode(values)
    except (OverflowError, ValueError) as exc:
        with pytest.raises(type(exc)):
            compiled.encode(values)
        return
    assert compiled.encode(values) == expected


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(text=layouts(), data=st.data())
def test_random_layouts_decode_and_encode_as_cantools(text: str, data) -> None:
    message = message_of(text)
    compiled, reference = compile_codec(message), CantoolsCodec(message)
    payload = data.draw(st.binary(min_size=message.length, max_size=message.length))
    got, want = compiled.decode(payload), reference.decode(payload)
    assert all(same(g, w) for g, w in zip(got, want, strict=True)), (compiled.source, got, want)
    encode_both(compiled, reference, list(want))  # decoded values encode back as cantools does
    encode_both(compiled, reference, values_for(data.draw, message))


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(text=layouts(), data=st.data())
def test_inlined_encode_as_cantools(text: str, data) -> None:
    """encode_lines, written into a function of the caller's, encodes as cantools: values
    promised to be small non-negative ints are packed as they are where their signal holds
    them, the rest rounded and checked; a literal False is left out."""
    message = message_of(text)
    values = values_for(data.draw, message)
    exprs, bounds = [], []
    for i, v in enumerate(values):
        promise = isinstance(v, int) and v >= 0 and data.draw(st.booleans())
        bounds.append(v + data.draw(st.sampled_from((0, 1, 1 << 20))) if promise else None)
        exprs.append("False" if v is False and data.draw(st.booleans()) else f"v{i}")
    lines, namespace, payload = encode_lines(message, exprs, bounds)
    args = ", ".join(f"v{i}" for i in range(len(values)))
    source = "\n".join([f"def encode({args}):", *lines, f"    return {payload}"]) + "\n"
    exec(compile(source, "<inlined encode>", "exec"), namespace)
    try:
        expected = CantoolsCodec(message).encode(values)
    except (OverflowError, ValueError) as exc:
        with pytest.raises(type(exc)):
            namespace["encode"](*values)
        return
    assert namespace["encode"](*values) == expected, source


@settings(max_examples=400, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(text=layouts(), data=st.data())
def test_inlined_decode_as_cantools(text: str, data) -> None:
    """decode_lines, written into a function of the caller's, gives cantools' values with
    cantools' types and signs of zero, for a payload of the frame's length; a signal the
    caller does not want (None) is left out, the others are as before."""
    message = message_of(text)
    payload = data.draw(st.binary(min_size=message.length, max_size=message.length))
    outs = [f"s{i}" if data.draw(st.booleans()) else None for i in range(len(message.signals))]
    wanted = [o for o in outs if o is not None]
    lines, namespace = decode_lines(message, "data", outs)
    back = f"    return ({''.join(o + ', ' for o in wanted)})"
    source = "\n".join(["def decode(data):", *lines, back]) + "\n"
    exec(compile(source, "<inlined decode>", "exec"), namespace)
    got = namespace["decode"](payload)
    want = [w for o, w in zip(outs, CantoolsCodec(message).decode(payload), strict=True) if o is not None]
    assert len(got) == len(want) and all(same(g, w) for g, w in zip(got, want, strict=True)), source


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(text=layouts(), data=st.data())
def test_inlined_encode_with_spans_as_cantools(text: str, data) -> None:
    """A value promised to lie in a span (as the daemon's saturated rates) encodes as cantools:
    the range check is left out only where the span's ends fit the signal's bits, so a value in
    the span never overflows silently, and a span that does not fit keeps cantools' error."""
    message = message_of(text)
    values = [v if isinstance(v, float) else float(v) for v in values_for(data.draw, message)]
    spans: list[tuple[float, float] | None] = []
    inside = []
    for v in values:
        if not math.isfinite(v) or not data.draw(st.booleans()):
            spans.append(None)
            inside.append(v)
            continue
        lo = data.draw(st.floats(min(-1e6, v), v, allow_nan=False))
        hi = data.draw(st.floats(v, max(1e6, v), allow_nan=False))
        spans.append((lo, hi))
        inside.append(data.draw(st.sampled_from((lo, v, hi))))
    lines, namespace, payload = encode_lines(message, [f"v{i}" for i in range(len(values))],
                                             [None] * len(values), spans=spans)
    args = ", ".join(f"v{i}" for i in range(len(values)))
    source = "\n".join([f"def encode({args}):", *lines, f"    return {payload}"]) + "\n"
    exec(compile(source, "<inlined encode>", "exec"), namespace)
    try:
        expected = CantoolsCodec(message).encode(inside)
    except (OverflowError, ValueError) as exc:
        with pytest.raises(type(exc)):
            namespace["encode"](*inside)
        return
    assert namespace["encode"](*inside) == expected, source


def test_a_span_inside_the_rate_signal_drops_its_check() -> None:
    """The daemon's case: CANICAL_RATE's rates saturated to their range need no range check,
    and a span one step wider keeps it."""
    message = cantools.database.load_file(str(DBC)).get_message_by_name("CANICAL_RATE")
    n = len(message.signals)
    exprs = [f"v{i}" for i in range(n)]
    fits = encode_lines(message, exprs, [None] * n, spans=[(-327.68, 327.67)] * 3 + [None] * (n - 3))[0]
    wide = encode_lines(message, exprs, [None] * n, spans=[(-327.69, 327.67)] * 3 + [None] * (n - 3))[0]
    assert sum("overflow" in line for line in fits) == n - 3
    assert sum("overflow" in line for line in wide) == n


@pytest.mark.parametrize("name", ["IMU_RAW", "IMU_AUX", "IMU_RATE", "CANICAL_RATE", "TABLE_REF"])
@settings(max_examples=300, deadline=None)
@given(data=st.data())
def test_project_frames_as_cantools(name: str, data) -> None:
    message = cantools.database.load_file(str(DBC)).get_message_by_name(name)
    compiled, reference = compile_codec(message), CantoolsCodec(message)
    payload = data.draw(st.binary(min_size=message.length, max_size=message.length))
    assert all(same(g, w) for g, w in zip(compiled.decode(payload), reference.decode(payload), strict=True))
    encode_both(compiled, reference, values_for(data.draw, message))


def test_rate_edges_round_and_saturate_as_cantools() -> None:
    """The corrected frame's rate signal at its range's ends, just past them, and at half steps."""
    message = cantools.database.load_file(str(DBC)).get_message_by_name("CANICAL_RATE")
    compiled, reference = compile_codec(message), CantoolsCodec(message)
    flags = [False] * 8 + [3, 15]
    for rate in (327.67, 327.675, 327.68, -327.68, -327.685, -327.69, 0.005, -0.005, 0.015, -0.0,
                 1e-12, math.nan, math.inf, -math.inf):
        encode_both(compiled, reference, [rate, -rate, 0.0, *flags])


def test_multiplexed_frame_falls_back_to_cantools_with_a_log_line(caplog) -> None:
    message = cantools.database.load_file(str(DBC)).get_message_by_name("CANICAL_STATUS")
    with caplog.at_level(logging.INFO, logger="canical.frames.compiler"):
        codec = codec_for(message)
    assert isinstance(codec, CantoolsCodec)
    assert "CANICAL_STATUS: layout not compiled (multiplexed); using cantools" in caplog.text
    assert isinstance(codec_for(cantools.database.load_file(str(DBC)).get_message_by_name("IMU_RAW")),
                      CompiledCodec)


def test_float_signal_is_not_compiled(caplog) -> None:
    text = ('VERSION ""\n\nNS_ :\n\nBS_:\n\nBU_: A\n\nBO_ 100 M: 8 A\n'
            ' SG_ F : 0|32@1- (1,0) [0|0] "" Vector__XXX\n\nSIG_VALTYPE_ 100 F : 1;\n')
    with caplog.at_level(logging.INFO, logger="canical.frames.compiler"):
        codec = codec_for(message_of(text))
    assert isinstance(codec, CantoolsCodec)
    assert "signal F is a float" in caplog.text


@pytest.mark.parametrize("signals", [0, 1, 3])
def test_the_cantools_codec_decodes_in_signal_order_whatever_the_count(signals: int) -> None:
    """The reference codec's values in signal order are a tuple for none, one or several signals
    (a message without signals is the reference's to handle: the compiler refuses it)."""
    lines = "".join(f' SG_ S{i} : {8 * i}|8@1- (0.5,{i}) [0|0] "" Vector__XXX\n' for i in range(signals))
    message = message_of(f'VERSION ""\n\nNS_ :\n\nBS_:\n\nBU_: A\n\nBO_ 100 M: 8 A\n{lines}\n')
    codec = codec_for(message) if signals == 0 else CantoolsCodec(message)
    payload = bytes([0xFE, 0x04, 0x80, 0, 0, 0, 0, 0])
    want = message.decode(payload, decode_choices=False)
    assert codec.decode(payload) == tuple(want[f"S{i}"] for i in range(signals))
    assert type(codec.decode(payload)) is tuple
