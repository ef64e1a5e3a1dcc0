"""The firmware's C evaluator (firmware/canical_eval.c) as a library: its build (strict C99, no libm,
build-time limits checked), its CRC, and what it refuses, code by code, as canical's own loader does."""

from __future__ import annotations

import json
import logging
import subprocess
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from support.firmware_build import (
    CODES,
    FIRMWARE,
    load_code,
    python_verdict,
)
from support.firmware_cases import (
    AXIS,
    SERIAL,
    TERMS,
    model_set,
    term_set,
)

from canical.device import firmware_eval
from canical.device.bank_payload import decode_set, encode_set
from canical.device.firmware_eval import CFLAGS, FirmwareCorrector, FirmwareRefusal
from canical.errors import CanicalError
from canical.sets.corrector import Corrector

# ----------------------------------------------------------------------------------------------
# Build and portability
# ----------------------------------------------------------------------------------------------


def test_object_needs_no_libm(tmp_path):
    """Compiled strictly for the device (NDEBUG: the internal asserts compiled out), the object's
    only external symbols are memset/memcmp/strlen/memcpy."""
    obj = tmp_path / "canical_eval.o"
    subprocess.run(
        ["cc", *CFLAGS[:5], "-pedantic", "-DNDEBUG", "-c", "-o", str(obj), str(FIRMWARE / "canical_eval.c")],
        check=True,
    )
    nm = subprocess.run(["nm", "-u", str(obj)], capture_output=True, text=True, check=True).stdout
    undefined = {line.split()[-1] for line in nm.splitlines() if line.strip()}
    assert undefined <= {"memset", "memcmp", "strlen", "memcpy"}, undefined


def _compile_with(tmp_path: Path, *defines: str) -> subprocess.CompletedProcess[str]:
    obj = tmp_path / "limits.o"
    cmd = ["cc", *CFLAGS[:5], "-pedantic", *defines, "-c", "-o", str(obj), str(FIRMWARE / "canical_eval.c")]
    return subprocess.run(cmd, capture_output=True, text=True, check=False)


@pytest.mark.parametrize(
    ("limit", "value"),
    [("CE_MAX_SEGMENTS", 256), ("CE_MAX_COEFFS", 0), ("CE_MAX_TERMS", 300), ("CE_MAX_INPUTS", 256),
     ("CE_MAX_DEPTH", 0)],
)
def test_out_of_range_limit_fails_the_build(tmp_path, limit, value):
    """A build-time limit that does not fit the uint8_t counting it stops the build with #error."""
    done = _compile_with(tmp_path, f"-D{limit}={value}")
    assert done.returncode != 0
    assert f"{limit} must be 1..255" in done.stderr, done.stderr


@pytest.mark.parametrize(
    ("defines", "message"),
    [(("-DCE_MAX_SPLINE_KNOTS=1",), "CE_MAX_SPLINE_KNOTS must be 2..255"),
     (("-DCE_MAX_SPLINE_KNOTS=256",), "CE_MAX_SPLINE_KNOTS must be 2..255"),
     (("-DCE_MAX_SPLINES=0",), "CE_MAX_SPLINES must be 1..CE_MAX_TERMS"),
     (("-DCE_MAX_TERMS=3", "-DCE_MAX_SPLINES=4"), "CE_MAX_SPLINES must be 1..CE_MAX_TERMS")],
)
def test_out_of_range_spline_limit_fails_the_build(tmp_path, defines, message):
    """A spline needs two knots and a uint8_t counts them; each spline slot belongs to a term."""
    done = _compile_with(tmp_path, *defines)
    assert done.returncode != 0
    assert message in done.stderr, done.stderr


def test_smallest_spline_limits_build(tmp_path):
    done = _compile_with(tmp_path, "-DCE_MAX_SPLINE_KNOTS=2", "-DCE_MAX_SPLINES=1")
    assert done.returncode == 0, done.stderr


def test_largest_limits_build(tmp_path):
    """Every limit at its largest (255) still compiles cleanly."""
    limits = ("CE_MAX_SEGMENTS", "CE_MAX_COEFFS", "CE_MAX_TERMS", "CE_MAX_INPUTS", "CE_MAX_DEPTH",
              "CE_MAX_SPLINE_KNOTS", "CE_MAX_SPLINES")
    done = _compile_with(tmp_path, *(f"-D{name}=255" for name in limits))
    assert done.returncode == 0, done.stderr


@given(st.binary(max_size=4096))
def test_crc32_is_zlibs(lib_for_hypothesis, data):
    assert lib_for_hypothesis.lib.ce_crc32(data, len(data)) == zlib.crc32(data)


# ----------------------------------------------------------------------------------------------
# Refusals
# ----------------------------------------------------------------------------------------------


def _edit(content: bytes, change) -> bytes:
    d = json.loads(content)
    change(d)
    return json.dumps(d, sort_keys=True, separators=(",", ":")).encode()


def _huge(d):
    n = 40
    lo, hi = d["model"]["span_raw"]
    d["model"]["knots_raw"] = list(np.linspace(lo, hi, n + 2)[1:-1])
    d["model"]["coefficients"] = [d["model"]["coefficients"][0]] * (n + 1)


def _term_edit(which: str, **fields):
    """Change the channel term of feature ``which`` (a stateful channel transform) in a bank's dict."""

    def change(d):
        (term,) = [t for t in d["terms"] if t["kind"] == "channel" and t["feature"] == which]
        term.update(fields)

    return change


REFUSALS = {
    "truncated": (lambda c: c[:-1], "CE_ERR_SYNTAX"),
    "white space": (lambda c: c.replace(b",", b", ", 1), "CE_ERR_NOT_CANONICAL"),
    "keys out of order": (
        lambda c: c.replace(b'{"created"', b'{"zz":0,"created"', 1),
        "CE_ERR_NOT_CANONICAL",
    ),
    "float spelling": (lambda c: c.replace(b'"schema":1', b'"schema":1.00'), "CE_ERR_NOT_CANONICAL"),
    "schema 2": (lambda c: _edit(c, lambda d: d.update(schema=2)), "CE_ERR_SCHEMA"),
    "NaN coefficient": (
        lambda c: c.replace(b'"coefficients":[[', b'"coefficients":[[NaN,', 1),
        "CE_ERR_FIELD",
    ),
    "row lengths differ": (
        lambda c: _edit(c, lambda d: d["model"]["coefficients"][1].append(0.5)),
        "CE_ERR_FIELD",
    ),
    "rows are not knots + 1": (lambda c: _edit(c, lambda d: d["model"]["knots_raw"].pop()), "CE_ERR_FIELD"),
    "knot outside the span": (
        lambda c: _edit(
            c, lambda d: d["model"]["knots_raw"].__setitem__(-1, d["model"]["span_raw"][1] + 1.0)
        ),
        "CE_ERR_FIELD",
    ),
    "huge segment count": (lambda c: _edit(c, _huge), "CE_ERR_LIMIT"),
    "unknown model kind": (
        lambda c: _edit(c, lambda d: d["model"].update(kind="spline")),
        "CE_ERR_MODEL_KIND",
    ),
    "unknown term kind": (
        lambda c: _edit(c, lambda d: d["terms"][0].update(kind="derivative")),
        "CE_ERR_TERM_KIND",
    ),
    "tau not positive": (
        lambda c: _edit(c, lambda d: [t.update(tau_s=-1.0) for t in d["terms"] if t["tau_s"] is not None]),
        "CE_ERR_FIELD",
    ),
    "lag without tau": (lambda c: _edit(c, _term_edit("lag", tau_s=None)), "CE_ERR_FIELD"),
    "derivative with tau 0": (lambda c: _edit(c, _term_edit("derivative", tau_s=0.0)), "CE_ERR_FIELD"),
    "derivative with tau as text": (lambda c: _edit(c, _term_edit("derivative", tau_s="1")), "CE_ERR_FIELD"),
    "lag of no channel": (lambda c: _edit(c, _term_edit("lag", channel=None)), "CE_ERR_FIELD"),
    "channel direction without threshold": (
        lambda c: _edit(c, _term_edit("direction", threshold_raw=None)),
        "CE_ERR_FIELD",
    ),
    "channel direction threshold negative": (
        lambda c: _edit(c, _term_edit("direction", threshold_raw=-0.5)),
        "CE_ERR_FIELD",
    ),
    "channel direction with tau negative": (
        lambda c: _edit(c, _term_edit("direction", tau_s=-1.0)),
        "CE_ERR_FIELD",
    ),
    "channel transform misspelt": (lambda c: _edit(c, _term_edit("lag", feature="Lag")), "CE_ERR_TERM_KIND"),
    "another sensor": (lambda c: _edit(c, lambda d: d["sensor"].update(id="4712")), "CE_ERR_SENSOR"),
    "another axis": (lambda c: _edit(c, lambda d: d["sensor"].update(axis="x")), "CE_ERR_AXIS"),
}


@pytest.mark.parametrize("name", list(REFUSALS))
def test_refuses_malformed_banks_with_a_code(lib, name):
    content, _ = encode_set(term_set(tuple(TERMS)))
    make, code = REFUSALS[name]
    bad = make(content)
    assert bad != content
    crc = zlib.crc32(bad)
    assert load_code(lib, bad, crc) == CODES[code]
    if code != "CE_ERR_LIMIT":  # a device limit; canical itself takes more segments
        assert python_verdict(bad, crc) is not None


def test_refuses_wrong_crc_narrow_span_and_missing_channel(lib):
    content, crc = encode_set(term_set(tuple(TERMS)))
    assert load_code(lib, content, crc) == 0
    assert load_code(lib, content, crc ^ 1) == CODES["CE_ERR_CRC"]
    assert load_code(lib, content, crc, rated=500.0) == CODES["CE_ERR_SPAN"]
    assert load_code(lib, content, crc, inputs=("temp_c",)) == CODES["CE_ERR_INPUT"]


def test_unknown_term_kind_falls_back_to_python(lib, caplog, monkeypatch):
    """A set canical accepts but this library cannot run (here: beyond its segment limit, as a term
    kind newer than the library would be) is corrected by the Python evaluator, with a log line."""
    content, _ = encode_set(model_set("segmented-inverse"))
    cset = decode_set(*(lambda b: (b, zlib.crc32(b)))(_edit(content, _huge)), "bank")
    monkeypatch.setattr(firmware_eval, "library", lambda: lib)
    with caplog.at_level(logging.WARNING, logger="canical.firmware"):
        corrector = firmware_eval.corrector_for(cset, serial=SERIAL, axis=AXIS)
    assert isinstance(corrector, Corrector)
    assert "CE_ERR_LIMIT" in caplog.text
    with pytest.raises(FirmwareRefusal):
        FirmwareCorrector(cset, lib=lib)
    monkeypatch.setattr(
        firmware_eval, "library", lambda: (_ for _ in ()).throw(CanicalError("no C compiler"))
    )
    assert isinstance(
        firmware_eval.corrector_for(model_set("forward-poly"), serial=SERIAL, axis=AXIS), Corrector
    )
    assert "no C compiler" in caplog.text



def test_agrees_with_canical_on_fields_it_does_not_read(lib):
    """Fields canical ignores (the other model kind's, statistics) are skipped alike, and numbers
    canical could never have written are refused even where nothing reads them."""
    forward, _ = encode_set(model_set("forward-poly"))
    segmented, _ = encode_set(model_set("segmented-inverse"))
    same = [
        _edit(forward, lambda d: d["model"].update(smoothness=5, knots_raw="none", scale=None)),
        _edit(segmented, lambda d: d["model"].update(rate_scale="none", rate_span_dps=[3.0])),
        _edit(segmented, lambda d: d["fit"].update(deep=[[[{"a": [1, 2.5, None, True, "x"]}]]])),
    ]
    for content in same:
        assert python_verdict(content, zlib.crc32(content)) is None
        assert load_code(lib, content, zlib.crc32(content), inputs=()) == 0
    for number in (b"1e999", b"-1e999", b"1e-999"):
        content = segmented.replace(b'"fit":{', b'"fit":{"a":' + number + b",", 1)
        assert python_verdict(content, zlib.crc32(content)) is not None
        assert load_code(lib, content, zlib.crc32(content)) == CODES["CE_ERR_NOT_CANONICAL"]

