"""The firmware's C evaluator (firmware/canical_eval.c): built here with the system compiler,
checked against canical's own evaluator and `canical apply`, and fuzzed under sanitizers."""

from __future__ import annotations

import copy
import json
import logging
import random
import struct
import subprocess
import sys
import zlib
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from support.firmware_cases import (
    ALL_TERMS,
    AXIS,
    CHANNELS,
    MODELS,
    SERIAL,
    TERMS,
    model_set,
    stream,
    term_set,
)

from canical.device import firmware_eval
from canical.device.bank_payload import decode_set, encode_set
from canical.device.firmware_eval import CFLAGS, FirmwareCorrector, FirmwareRefusal, Library, compile_library
from canical.errors import CanicalError
from canical.sets import coefficient_file
from canical.sets.admission import DeviceLimits, admission_problem
from canical.sets.corrector import Corrector
from canical.sets.terms import term_from_dict

FIRMWARE = Path(__file__).resolve().parents[2] / "firmware"
SANITIZE = (
    "-O1",
    "-g",
    "-fsanitize=address,undefined",
    "-fno-sanitize-recover=all",
    "-fno-omit-frame-pointer",
)
RATED = 50.0
CE_MAX_SEGMENTS = 16
N_SAMPLES = 1_000_000
TOLERANCE_DPS = 1e-4
CODES = {v: k for k, v in firmware_eval.ERROR_NAMES.items()}


@pytest.fixture(scope="module")
def lib(tmp_path_factory) -> Library:
    """Built from firmware/ with -std=c99 -Wall -Wextra -Werror -O2 (a warning fails the test)."""
    out = tmp_path_factory.mktemp("fw") / "libcanical_eval.so"
    compile_library(out, sources=FIRMWARE)
    return Library(out)


@pytest.fixture(scope="module")
def sanitized_driver(tmp_path_factory) -> Path:
    """firmware/fuzz_driver.c with the library, under AddressSanitizer and UBSan."""
    exe = tmp_path_factory.mktemp("fuzz") / "fuzz_driver"
    cmd = [
        "cc",
        *CFLAGS[:5],
        *SANITIZE,
        "-o",
        str(exe),
        str(FIRMWARE / "fuzz_driver.c"),
        str(FIRMWARE / "canical_eval.c"),
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    return exe


def seeds() -> list[tuple[bytes, int]]:
    """Valid banks: every model kind, and a segmented set with every term kind."""
    sets = [model_set(m) for m in MODELS] + [term_set(tuple(TERMS))]
    return [encode_set(s) for s in sets]


def python_verdict(content: bytes, crc: int) -> str | None:
    """Why canical's own device code refuses a bank (None: it accepts it)."""
    try:
        cset = decode_set(content, crc, "bank")
    except CanicalError as exc:
        return str(exc)
    return admission_problem(cset, AXIS, DeviceLimits(SERIAL, {AXIS: RATED}))


def load_code(
    lib: Library,
    content: bytes,
    crc: int,
    *,
    axis: str = AXIS,
    rated: float = RATED,
    inputs: tuple[str, ...] = CHANNELS,
) -> int:
    import ctypes

    device = firmware_eval.make_device(SERIAL, axis, rated, inputs)
    buf = ctypes.create_string_buffer(lib.set_size)
    return int(lib.lib.ce_load(buf, content, len(content), crc, ctypes.byref(device)))


# ----------------------------------------------------------------------------------------------
# Build and portability
# ----------------------------------------------------------------------------------------------


def test_object_needs_no_libm(tmp_path):
    """Compiled strictly, the object's only external symbols are memset/memcmp/strlen."""
    obj = tmp_path / "canical_eval.o"
    subprocess.run(
        ["cc", *CFLAGS[:5], "-pedantic", "-c", "-o", str(obj), str(FIRMWARE / "canical_eval.c")], check=True
    )
    nm = subprocess.run(["nm", "-u", str(obj)], capture_output=True, text=True, check=True).stdout
    undefined = {line.split()[-1] for line in nm.splitlines() if line.strip()}
    assert undefined <= {"memset", "memcmp", "strlen", "memcpy"}, undefined


@given(st.binary(max_size=4096))
def test_crc32_is_zlibs(lib_for_hypothesis, data):
    assert lib_for_hypothesis.lib.ce_crc32(data, len(data)) == zlib.crc32(data)


@pytest.fixture(scope="module")
def lib_for_hypothesis(lib):
    return lib


# ----------------------------------------------------------------------------------------------
# Same rates as canical apply
# ----------------------------------------------------------------------------------------------

CASES = {f"model {m}": (lambda m=m: model_set(m)) for m in MODELS}
CASES.update({f"term {t}": (lambda t=t: term_set((t,))) for t in ALL_TERMS})
CASES["every term at once"] = lambda: term_set(tuple(TERMS))


@pytest.mark.parametrize("case", list(CASES))
def test_float32_rates_equal_apply_on_a_million_samples(lib, case):
    """The evaluator `canical apply` runs (Corrector.correct) and the C library, sample by sample."""
    cset = CASES[case]()
    raw, inputs = stream(cset, N_SAMPLES, seed=len(case))
    expected, expected_oos = Corrector(cset).correct(raw, inputs)
    rate, oos = FirmwareCorrector(cset, rated_range_dps=RATED, lib=lib).correct(raw, inputs)
    assert 0 < expected_oos.sum() < N_SAMPLES  # both sides of the span and inside it are exercised
    np.testing.assert_array_equal(oos, expected_oos)
    worst = float(np.max(np.abs(rate - expected)))
    assert worst <= TOLERANCE_DPS, f"{case}: largest difference {worst:.2e} deg/s"


def test_cli_apply_output_equals_firmware(lib, tmp_path):
    """`canical apply` end to end (CSV in, CSV out) against the C library on the same rows."""
    cset = term_set(tuple(TERMS))
    path = tmp_path / "set.yaml"
    path.write_text(coefficient_file.dumps(cset))
    raw, inputs = stream(cset, 100_000, seed=7)
    csv = tmp_path / "drive.csv"
    cols = ["time_s", "raw", *CHANNELS]
    data = np.column_stack([inputs["time_s"], raw, *(inputs[c] for c in CHANNELS)])
    np.savetxt(
        csv, data, delimiter=",", header=",".join(cols), comments="", fmt=["%.2f", "%d", "%.6f", "%.6f"]
    )
    out = tmp_path / "out.csv"
    subprocess.run(
        [sys.executable, "-m", "canical", "apply", str(path), str(csv), "-o", str(out)],
        check=True,
        capture_output=True,
    )
    table = np.loadtxt(out, delimiter=",", skiprows=1)
    back = {c: table[:, cols.index(c)] for c in cols}
    rate, oos = FirmwareCorrector(cset, lib=lib).correct(back["raw"], back)
    np.testing.assert_array_equal(oos, table[:, -1].astype(bool))
    assert float(np.max(np.abs(rate - table[:, -2]))) <= TOLERANCE_DPS + 5e-7  # apply prints 6 decimals


def test_per_sample_path_carries_state_like_the_block(lib):
    cset = term_set(tuple(TERMS))
    raw, inputs = stream(cset, 3000, seed=3)
    block, block_oos = FirmwareCorrector(cset, lib=lib).correct(raw, inputs)
    one = FirmwareCorrector(cset, lib=lib)
    rows = [one.correct_one(r, {k: v[i] for k, v in inputs.items()}) for i, r in enumerate(raw)]
    np.testing.assert_array_equal(np.array([r for r, _ in rows], dtype=np.float32), block.astype(np.float32))
    np.testing.assert_array_equal([o for _, o in rows], block_oos)


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


# ----------------------------------------------------------------------------------------------
# Fuzzing under AddressSanitizer and UBSan
# ----------------------------------------------------------------------------------------------


def _records(cases: list[tuple[bytes, int]]) -> bytes:
    return b"".join(struct.pack("<II", len(c), crc) + c for c, crc in cases)


def run_driver(
    exe: Path, args: list[str], tmp_path: Path, cases: list[tuple[bytes, int]], sample_every: int = 0
) -> str:
    path = tmp_path / "records.bin"
    path.write_bytes(_records(cases))
    mode, *rest = args
    cmd = [str(exe), mode, str(path), *rest, str(SERIAL), AXIS, str(RATED), *CHANNELS]
    done = subprocess.run(
        cmd,
        capture_output=True,
        text=True,
        check=False,
        timeout=600,
        env={
            "ASAN_OPTIONS": "abort_on_error=0:exitcode=99",
            "UBSAN_OPTIONS": "exitcode=99",
            "CE_SAMPLE_EVERY": str(sample_every),
        },
    )
    assert done.returncode == 0 and "runtime error" not in done.stderr and "Sanitizer" not in done.stderr, (
        done.stderr[-3000:]
    )
    return done.stdout


NUMBER_SLOTS = ("v0", "scale", "coefficient", "knot", "span")
BAD_NUMBERS = (
    "NaN",
    "-NaN",
    "Infinity",
    "-Infinity",
    "1e999",
    "-1e999",
    "1E5",
    "01",
    "1.",
    ".5",
    "+1",
    "0x10",
)


def malformed(base: dict, rng: random.Random) -> tuple[bytes, int, str]:
    """One structurally malformed bank derived from a valid set (CRC matching unless 'crc')."""
    d = copy.deepcopy(base)
    m = d["model"]
    piecewise = m["kind"] != "forward-poly"
    kind = rng.choice(
        (
            "truncate",
            "crc",
            "row-length",
            "knot-count",
            "span-length",
            "huge-segments",
            "bad-number",
            "wrong-type",
            "missing",
            "non-canonical",
            "schema",
            "term",
            "channel-term",
            "order-of-knots",
            "identity",
        )
    )
    marker = "@@BAD@@"
    bad_number = rng.choice(BAD_NUMBERS)
    if kind in ("truncate", "crc", "non-canonical"):
        pass
    elif kind == "row-length" and piecewise:
        row = rng.choice(m["coefficients"])
        row.pop() if len(row) > 1 and rng.random() < 0.5 else row.append(rng.uniform(-1, 1))
    elif kind == "row-length":
        m["coefficients"] = m["coefficients"][:1]
    elif kind == "knot-count" and piecewise:
        if m["knots_raw"] and rng.random() < 0.5:
            m["knots_raw"].pop(rng.randrange(len(m["knots_raw"])))
        else:
            m["coefficients"].append(list(m["coefficients"][0]))
    elif kind == "span-length":
        key = "span_raw" if piecewise or rng.random() < 0.5 else "rate_span_dps"
        m[key] = m[key][:1] if rng.random() < 0.5 else [*m[key], m[key][1] + 1.0]
    elif kind == "huge-segments" and piecewise:
        n = rng.choice(
            (CE_MAX_SEGMENTS, 17, 64, 300, rng.randrange(16, 2000), 20_000 if rng.random() < 0.01 else 99)
        )
        lo, hi = m["span_raw"]
        step = (hi - lo) / (n + 1)
        m["knots_raw"] = [lo + step * (i + 1) for i in range(n - 1)]
        m["coefficients"] = [[1.5] * len(m["coefficients"][0])] * n
    elif kind == "bad-number" or kind == "huge-segments":
        slot = rng.choice(NUMBER_SLOTS)
        if slot == "v0":
            d["v0"] = marker
        elif slot == "scale":
            m["scale" if piecewise else "rate_scale"] = marker
        elif slot == "knot" and piecewise and m["knots_raw"]:
            m["knots_raw"][rng.randrange(len(m["knots_raw"]))] = marker
        elif slot == "span":
            m["span_raw"][rng.randrange(2)] = marker
        else:
            rows = m["coefficients"] if piecewise else [m["coefficients"]]
            row = rng.choice(rows)
            row[rng.randrange(len(row))] = marker
    elif kind == "wrong-type":
        value = rng.choice(("1", [], {}, None, True, [1.0], "x"))
        target = rng.choice(
            (
                "v0",
                "sensor",
                "units",
                "model",
                "terms",
                "scale",
                "kind",
                "knots",
                "coefficients",
                "span",
                "id",
                "axis",
            )
        )
        if target in ("v0", "sensor", "units", "model", "terms"):
            d[target] = value if value not in ([], {}) else ({} if target == "terms" else None)
        elif target in ("id", "axis"):
            d["sensor"][target] = value if isinstance(value, str) is False else ""
        else:
            key = {
                "scale": "scale" if piecewise else "rate_scale",
                "knots": "knots_raw" if piecewise else "kind",
                "span": "span_raw",
            }.get(target, target)
            m[key] = value if value != [1.0] or key != "coefficients" else [[1.0], 2.0]
            if m[key] in ([], {}) and key == "coefficients":
                m[key] = None
    elif kind == "missing":
        where, key = rng.choice(
            (
                (d, "v0"),
                (d, "model"),
                (d, "sensor"),
                (d, "units"),
                (d, "schema"),
                (m, "kind"),
                (m, "span_raw"),
                (m, "coefficients"),
                (m, "knots_raw" if piecewise else "rate_span_dps"),
                (m, "scale" if piecewise else "rate_scale"),
                (d["sensor"], "id"),
                (d["sensor"], "axis"),
            )
        )
        where.pop(key)
    elif kind == "schema":
        d["schema"] = rng.choice((0, 2, -1, 1.5, "1", None))
    elif kind == "term":
        term = {
            "kind": "direction",
            "channel": None,
            "feature": "sign",
            "form": "bias",
            "coefficient": 1.0,
            "reference": 0.0,
            "tau_s": None,
            "threshold_raw": 5.0,
        }
        change = rng.choice(("kind", "feature", "form", "tau", "threshold", "channel", "coefficient"))
        if change == "kind":
            term["kind"] = rng.choice(("derivative", "lag", "hysteresis", "", "Direction"))
        elif change == "feature":
            term["feature"] = rng.choice(("warmup", "offset", "slope2", None))
        elif change == "form":
            term["form"] = rng.choice(("gain", "", None, 1))
        elif change == "tau":
            term.update(feature="slope", tau_s=rng.choice((None, 0.0, -1.0)))
        elif change == "threshold":
            term["threshold_raw"] = rng.choice((None, 0.0, -3.0))
        elif change == "channel":
            term.update(kind="channel", feature="offset", channel=rng.choice(("", None, 5)))
        else:
            term["coefficient"] = rng.choice((None, "1", marker))
        d["terms"] = [*d["terms"], term]
        if not piecewise:
            d["terms"] = [dict(term, kind="time", feature="linear")]  # terms need a segmented model
    elif kind == "channel-term":  # a stateful channel transform with a parameter wrong
        feature = rng.choice(("lag", "derivative", "direction"))
        term = dict(ALL_TERMS[f"channel-{feature}"], reference=0.0)
        term.setdefault("tau_s", None)
        term.setdefault("threshold_raw", None)
        need = "threshold_raw" if feature == "direction" else "tau_s"
        change = rng.choice(
            ("missing", "not positive", "wrong type", "other's", "channel", "feature", "coefficient")
        )
        if change == "missing":
            term[need] = None
        elif change == "not positive":
            term[need] = rng.choice((0.0, -1.0, -1e-300, -5e30))
        elif change == "wrong type":
            term[need] = rng.choice(("1", [2.5], {}, True, marker))
        elif change == "other's":  # the optional one given, but not positive
            term["threshold_raw" if need == "tau_s" else "tau_s"] = rng.choice((0.0, -2.0, marker))
        elif change == "channel":
            term["channel"] = rng.choice(("", None, 5, [], marker))
        elif change == "feature":
            term["feature"] = rng.choice(("Lag", "lag ", "d/dt", "derivative2", "sign", "slope", ""))
        else:
            term["coefficient"] = rng.choice((None, "1", marker, False))
        d["terms"] = [*d["terms"], term] if piecewise else [term]
    elif kind == "order-of-knots" and piecewise and len(m["knots_raw"]) >= 2:
        m["knots_raw"][0], m["knots_raw"][1] = m["knots_raw"][1], m["knots_raw"][0]
    elif kind == "order-of-knots":
        m["span_raw"] = m["span_raw"][::-1]
    else:  # identity
        if rng.random() < 0.5:
            d["sensor"]["id"] = rng.choice(("4712", "04711", "sim", "47110"))
        else:
            d["sensor"]["axis"] = rng.choice(("x", "y", "Z", "zz"))
    text = json.dumps(d, sort_keys=True, separators=(",", ":")).replace(f'"{marker}"', bad_number)
    content = text.encode()
    if kind == "truncate":
        content = content[: rng.randrange(len(content))]
    elif kind == "non-canonical":  # white space before a key, or a key out of order
        gap = rng.choice((b" ", b"\n", b"\t", b"\r"))
        content = (
            content.replace(b',"', b"," + gap + b'"', 1) if rng.random() < 0.5 else b'{"~":1,' + content[1:]
        )
    crc = zlib.crc32(content)
    if kind == "crc":
        crc ^= 1 << rng.randrange(32)
    return content, crc, kind


N_STRUCTURED = 100_000


def test_fuzz_100k_structured_malformed_banks_all_refused(sanitized_driver, tmp_path):
    """Truncated, wrong CRC, wrong lengths, huge segment counts, NaN/Infinity numbers, wrong types,
    missing fields, bad terms, non-canonical bytes: every one refused, no sanitizer report."""
    rng = random.Random(13)
    bases = [json.loads(c) for c, _ in seeds()]
    cases = [malformed(rng.choice(bases), rng) for _ in range(N_STRUCTURED)]
    out = run_driver(sanitized_driver, ["cases"], tmp_path, [(c, crc) for c, crc, _ in cases])
    codes = [int(x) for x in out.split()]
    assert len(codes) == N_STRUCTURED
    accepted = [cases[i][2] for i, code in enumerate(codes) if code == 0]
    assert not accepted, f"accepted malformed banks of kinds {sorted(set(accepted))}"
    # canical's own device code refuses them too (a sample: it is slower); only the segment limit
    # is the firmware's own
    for content, crc, kind in cases[:1000]:
        if kind != "huge-segments":
            assert python_verdict(content, crc) is not None, kind


def _escaped_key(value) -> bool:
    """Whether any object key needs a JSON escape (the C library reads plain keys only)."""
    if isinstance(value, dict):
        return any(not k.isascii() or not k.isprintable() or '"' in k or "\\" in k or _escaped_key(v)
                   for k, v in value.items())  # fmt: skip
    return isinstance(value, list) and any(_escaped_key(v) for v in value)


def test_fuzz_random_mutations_under_sanitizers(sanitized_driver, tmp_path):
    """150,000 random byte-level mutations (CRC recomputed for most): no sanitizer report, and the
    C library's verdict is canical's own (checked on samples: Python's check is the slow part):
    what it accepts canical accepts, up to non-shortest float spellings; what it refuses canical
    refuses, except for the device's own rules (limits, channels it has) and escaped keys."""
    n = 150_000
    out = run_driver(sanitized_driver, ["mutate", str(n), "1313"], tmp_path, seeds(), sample_every=30)
    *lines, summary = out.splitlines()
    assert summary.startswith(f"cases {n} accepted ")
    fields = ([*ln.split(" "), ""][:3] for ln in lines)
    rows = [(int(code), int(crc, 16), bytes.fromhex(hexed)) for code, crc, hexed in fields]
    accepted = [r for r in rows if r[0] == 0]
    refused = [r for r in rows if r[0] != 0]
    assert accepted and len(refused) >= 3000, (len(accepted), len(refused))
    spelling_only = 0
    rng = random.Random(5)
    for _, crc, content in rng.sample(accepted, min(3000, len(accepted))):
        verdict = python_verdict(content, crc)
        if verdict is not None:
            assert "canonical form" in verdict, verdict  # a digit changed to a non-shortest spelling
            spelling_only += 1
    assert spelling_only <= len(accepted) // 2
    device_rules = {CODES["CE_ERR_LIMIT"], CODES["CE_ERR_INPUT"]}
    for code, crc, content in rng.sample(refused, 3000):
        if python_verdict(content, crc) is None:
            escaped = code == CODES["CE_ERR_FIELD"] and _escaped_key(json.loads(content))
            assert code in device_rules or escaped, (code, content)


@settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(seed=st.integers(0, 2**32 - 1), base=st.sampled_from(range(len(MODELS) + 1)))
def test_property_structured_malformed_refused_by_both(lib_for_hypothesis, seed, base):
    content, crc, kind = malformed(json.loads(seeds()[base][0]), random.Random(seed))
    assert load_code(lib_for_hypothesis, content, crc) < 0, kind
    if kind != "huge-segments":
        assert python_verdict(content, crc) is not None, kind


# ----------------------------------------------------------------------------------------------
# The emulated IMU runs the firmware
# ----------------------------------------------------------------------------------------------


def test_emulated_imu_corrects_its_frames_with_the_firmware(caplog):
    """After an activation the device builds its correctors in C; its IMU_RATE frames carry the
    rates of canical's evaluator (to the frame's 0.01 deg/s) on the inputs its own frames carry."""
    import canopen

    from canical.device.emulated_imu import EmulatedImu, EmulatorConfig
    from canical.imu_dictionary import pack_active

    cset = term_set(tuple(TERMS))
    transforms = {t["feature"] for t in cset.terms if t["kind"] == "channel"}
    assert transforms >= {"lag", "derivative", "direction"}  # the stateful channel terms run in C too
    imu = EmulatedImu(EmulatorConfig(serial=SERIAL), canopen.Network())
    content, crc = encode_set(cset)
    imu.store.write_content(AXIS, "B", content)
    imu.store.write_crc(AXIS, "B", crc)
    imu.store.activate(pack_active({AXIS: "B"}))
    with caplog.at_level(logging.INFO, logger="canical.imu"):
        correctors = imu.device_correctors()
    assert isinstance(correctors[AXIS], FirmwareCorrector) and set(correctors) == {AXIS}
    assert "corrected on the device with the firmware evaluator (C)" in caplog.text
    reference = Corrector(cset)
    raw, inputs = stream(cset, 400, seed=11)
    for k, counts in enumerate(raw.astype(int), start=1):
        aux = imu.frames.aux(inputs["supply_v"][k - 1], inputs["time_s"][k - 1], k)
        frame = imu.frames.raw((0, 0, int(counts)), inputs["temp_c"][k - 1], k)
        rate_id, rate_data = imu._corrected(correctors, 0, *frame, *aux, k)
        sent = imu.frames.decode(rate_id, rate_data).values
        decoded_in = {"temp_c": imu.frames.decode(*frame).values["Temperature"],
                      "supply_v": imu.frames.decode(*aux).values["SupplyVoltage"],
                      "time_s": imu.frames.decode(*aux).values["Uptime"]}  # fmt: skip
        expected, oos = reference.correct_one(float(counts), decoded_in)
        assert abs(sent["RateZ"] - max(-327.68, min(327.67, expected))) <= 0.0051
        assert sent["OutOfSpanZ"] == int(oos) and sent["UncalibratedX"] == 1


@st.composite
def random_sets(draw):
    """Valid sets far from any fit: random segment points, orders, coefficients, zero bias, terms."""
    from dataclasses import replace

    base = term_set(())
    v0 = draw(st.floats(-800.0, 800.0))
    lo, hi = draw(st.floats(-32000.0, -4000.0)), draw(st.floats(4000.0, 32000.0))
    if draw(st.booleans()):
        order = draw(st.integers(1, 9))
        cuts = draw(st.lists(st.floats(0.02, 0.98), max_size=CE_MAX_SEGMENTS - 1, unique=True))
        knots = sorted({lo + f * (hi - lo) for f in cuts})
        scale = max(-lo, hi)
        rows = [[draw(st.floats(-5, 5)), draw(st.floats(20, 80)), *draw(st.lists(st.floats(-5, 5),
                 min_size=order - 1, max_size=order - 1))] for _ in range(len(knots) + 1)]  # fmt: skip
        model = {"kind": "segmented-inverse", "knots_raw": [k + v0 for k in knots], "segment_points_dps": [],
                 "scale": scale, "coefficients": rows, "smoothness": None, "span_raw": [lo + v0, hi + v0],
                 "out_of_span": "linear-extrapolation"}  # fmt: skip
        names = draw(st.lists(st.sampled_from(sorted(ALL_TERMS)), unique=True, max_size=4))
        terms = tuple(
            dict(ALL_TERMS[n], coefficient=ALL_TERMS[n]["coefficient"] * draw(st.floats(-2, 2)))
            for n in names
        )
    else:
        a1 = draw(st.floats(5000, 30000))
        coeffs = [
            draw(st.floats(-100, 100)),
            a1,
            *(draw(st.floats(-0.1, 0.1)) * a1 for _ in range(draw(st.integers(0, 3)))),
        ]
        rate_scale = draw(st.floats(50, 300))
        model = {"kind": "forward-poly", "coefficients": coeffs, "rate_scale": rate_scale,
                 "rate_span_dps": [-rate_scale, rate_scale * draw(st.floats(0.5, 1.0))],
                 "span_raw": [lo + v0, hi + v0], "out_of_span": "linear-extrapolation"}  # fmt: skip
        terms = ()
    cset = replace(base, v0=v0, model=model, terms=tuple(term_from_dict(t).to_dict() for t in terms))
    return coefficient_file.loads(coefficient_file.dumps(cset))


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cset=random_sets(), seed=st.integers(0, 1000))
def test_property_any_valid_set_evaluates_like_canical(lib_for_hypothesis, cset, seed):
    """Not only fitted sets: any valid set within the limits gives canical's rates (to float32
    rounding: 2e-6 of the rate's size) and the same out-of-span flags."""
    raw, inputs = stream(cset, 3000, seed=seed)
    expected, expected_oos = Corrector(cset).correct(raw, inputs)
    fw = FirmwareCorrector(cset, lib=lib_for_hypothesis)
    rate, oos = fw.correct(raw, inputs)
    np.testing.assert_array_equal(oos, expected_oos)
    np.testing.assert_allclose(rate, expected, rtol=2e-6, atol=1e-5)
    import ctypes

    lib = lib_for_hypothesis.lib
    fixed = ctypes.create_string_buffer(lib_for_hypothesis.fixed_size)
    if lib.ce_fixed_from(fixed, fw._set) != 0:
        assert cset.terms or cset.kind == "forward-poly"  # the fixed form's scope
        return
    out = ctypes.c_int32()
    for r, e, o in zip(raw.astype(np.int32).tolist(), expected.tolist(), expected_oos.tolist(), strict=True):
        assert lib.ce_fixed_eval(fixed, r, ctypes.byref(out)) == o
        assert abs(out.value / 65536.0 - e) < 1e-3


#: Coefficients of the stateful channel terms per form (raw units per unit of x, or relative gain).
TRANSFORM_COEFFICIENTS = {
    ("lag", "bias"): 2.8,
    ("lag", "scale"): 1e-4,
    ("derivative", "bias"): 150.0,
    ("derivative", "scale"): 0.02,
    ("direction", "bias"): 4.5,
    ("direction", "scale"): 3e-4,
}


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(
    feature=st.sampled_from(("lag", "derivative", "direction")),
    form=st.sampled_from(("bias", "scale")),
    tau_ms=st.integers(5, 3_000),  # the lag's phase after τ within the stream's seconds
    threshold_steps=st.integers(1, 40),
    n=st.integers(2, 800),
    longest_step_ms=st.integers(0, 80),
    start_ms=st.one_of(st.integers(0, 2**32 - 1), st.integers(2**32 - 20_000, 2**32 - 1)),  # wraps
    seed=st.integers(0, 1000),
)
def test_property_channel_transforms_on_any_time_spacing(
    lib_for_hypothesis, feature, form, tau_ms, threshold_steps, n, longest_step_ms, start_ms, seed
):
    """A channel's lag, derivative and direction, sample by sample as the device runs them, with
    samples at any spacing (repeated times too) and from any point of the millisecond counter
    (it wraps after 49.7 days; canical's seconds do not): canical's rates within 1e-4 deg/s and
    its out-of-span flags.

    τ lies half a millisecond off the millisecond grid and the threshold half a step off the
    channel's 0.01 grid: exactly at τ after the first sample, or a move of exactly the
    threshold, canical's double-precision comparison falls either way by rounding, while the
    device decides on whole milliseconds and float32 values."""
    from dataclasses import replace

    rng = np.random.default_rng(seed)
    term = {"kind": "channel", "channel": "temp_c", "feature": feature, "form": form,
            "coefficient": TRANSFORM_COEFFICIENTS[feature, form], "reference": 25.0,
            "tau_s": (tau_ms + 0.5) / 1000.0 if feature != "direction" else None,
            "threshold_raw": (threshold_steps + 0.5) * 0.01 if feature == "direction" else None}  # fmt: skip
    base = model_set("segmented-inverse")
    one = replace(base, terms=(term_from_dict(term).to_dict(),))
    cset = coefficient_file.loads(coefficient_file.dumps(one))
    raw, _ = stream(cset, n, seed=seed)
    time_s = (start_ms + np.cumsum(rng.integers(0, longest_step_ms + 1, n))) / 1000.0
    temp = (2500 + np.cumsum(rng.integers(-4, 5, n))) * 0.01
    python, device = Corrector(cset), FirmwareCorrector(cset, lib=lib_for_hypothesis)
    for r, t, v in zip(raw.tolist(), time_s.tolist(), temp.tolist(), strict=True):
        inputs = {"time_s": t, "temp_c": v}
        expected, expected_oos = python.correct_one(r, inputs)
        rate, oos = device.correct_one(r, inputs)
        assert oos == expected_oos
        assert abs(rate - expected) <= TOLERANCE_DPS, (t, rate, expected)


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


PIECEWISE = [m for m in MODELS if m != "forward-poly"]


@pytest.mark.parametrize("model", PIECEWISE)
def test_fixed_point_form_within_a_tenth_of_the_frame_lsb(lib, model):
    """The integer-only form (ce_fixed_*) of a piecewise set on 1,000,000 integer samples: within
    0.001 deg/s of canical's rates (the corrected frame's LSB is 0.01) and the same flags."""
    import ctypes

    cset = model_set(model)
    fixed = ctypes.create_string_buffer(lib.fixed_size)
    assert lib.lib.ce_fixed_from(fixed, FirmwareCorrector(cset, lib=lib)._set) == 0
    raw, inputs = stream(cset, N_SAMPLES, seed=21)
    expected, expected_oos = Corrector(cset).correct(raw, inputs)
    out = ctypes.c_int32()
    evaluate, ref = lib.lib.ce_fixed_eval, ctypes.byref(out)
    rate = np.empty(N_SAMPLES)
    oos = np.empty(N_SAMPLES, dtype=bool)
    for i, r in enumerate(raw.astype(np.int32).tolist()):
        oos[i] = evaluate(fixed, r, ref)
        rate[i] = out.value
    np.testing.assert_array_equal(oos, expected_oos)
    assert float(np.max(np.abs(rate / 65536.0 - expected))) < 1e-3


def test_fixed_point_form_refuses_what_it_cannot_run(lib):
    import ctypes

    fixed = ctypes.create_string_buffer(lib.fixed_size)
    forward = FirmwareCorrector(model_set("forward-poly"), lib=lib)
    with_terms = FirmwareCorrector(term_set(("direction-sign",)), lib=lib)
    assert lib.lib.ce_fixed_from(fixed, forward._set) == CODES["CE_ERR_MODEL_KIND"]
    assert lib.lib.ce_fixed_from(fixed, with_terms._set) == CODES["CE_ERR_TERM_KIND"]
    out = ctypes.c_int32()
    assert lib.lib.ce_fixed_eval(fixed, 0, ctypes.byref(out)) == CODES["CE_ERR_ARG"]  # nothing loaded


@st.composite
def centred_calibrations(draw):
    """Piecewise sets shaped like real calibrations of high order: each wide segment's polynomial
    is a smooth local curve (rate near R*u plus a few % of nonlinearity across the segment),
    written as canical writes it, in powers of u = dV / scale. Away from u = 0 that gives large
    alternating coefficients (hundreds to millions times the rate) that cancel in float32."""
    import itertools
    from dataclasses import replace
    from math import comb

    v0 = draw(st.floats(-800.0, 800.0))
    lo, hi = -draw(st.floats(8000.0, 32000.0)), draw(st.floats(8000.0, 32000.0))
    scale = max(-lo, hi)
    segments, order = draw(st.integers(3, 6)), draw(st.integers(4, 9))
    inner = sorted(draw(st.lists(st.floats(0.1, 0.9), min_size=segments - 1, max_size=segments - 1)))
    edges = [lo, *(lo + f * (hi - lo) for f in inner), hi]
    if min(b - a for a, b in itertools.pairwise(edges)) < 0.08 * (hi - lo):
        edges = [lo + (hi - lo) * s / segments for s in range(segments + 1)]  # wide segments only
    rated = draw(st.floats(50.0, 300.0))  # deg/s at |u| = 1
    rows = []
    for a, b in itertools.pairwise(edges):
        mu, hu = 0.5 * (a + b) / scale, 0.5 * (b - a) / scale
        bends = [draw(st.sampled_from((-1, 1))) * draw(st.floats(0.005, 0.03)) for _ in range(order - 1)]
        q = [rated * mu, rated * hu, *(rated * b for b in bends)]
        # p(u) = q((u - mu) / hu): binomial re-expansion in powers of u, in double
        p = [0.0] * (order + 1)
        for k, qk in enumerate(q):
            for j in range(k + 1):
                p[j] += qk * comb(k, j) * (-mu) ** (k - j) / hu**k
        rows.append(p)
    model = {"kind": "segmented-inverse", "knots_raw": [e + v0 for e in edges[1:-1]],
             "segment_points_dps": [], "scale": scale, "coefficients": rows, "smoothness": None,
             "span_raw": [lo + v0, hi + v0], "out_of_span": "linear-extrapolation"}  # fmt: skip
    cset = replace(term_set(()), v0=v0, model=model, terms=())
    return coefficient_file.loads(coefficient_file.dumps(cset))


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(cset=centred_calibrations(), seed=st.integers(0, 1000))
def test_property_large_alternating_coefficients_hold_the_bound(lib_for_hypothesis, cset, seed):
    """Wide segments with large alternating coefficients (as high-order calibrations produce):
    the float32 rates stay within 1e-4 deg/s of canical's, and the fixed-point form accepts the
    set and stays within 1e-3 deg/s (a tenth of the frame's LSB)."""
    import ctypes

    raw, inputs = stream(cset, 20_000, seed=seed)
    expected, expected_oos = Corrector(cset).correct(raw, inputs)
    fw = FirmwareCorrector(cset, lib=lib_for_hypothesis)
    rate, oos = fw.correct(raw, inputs)
    np.testing.assert_array_equal(oos, expected_oos)
    inside = ~expected_oos
    worst = float(np.max(np.abs(rate - expected)[inside]))
    # float32 keeps ~7 digits: an order-9 Horner sum in [-1, 1] is good to a few ulps of the rate,
    # and at 300 deg/s one ulp is 3e-5 deg/s. So these synthetic sets (up to 300 deg/s, order 9)
    # are held to 1e-4 deg/s or 16 ulps of the largest rate, whichever is larger; the sets canical
    # writes are held to 1e-4 deg/s on a million samples each (the tests above).
    ulp_bound = 16 * 2.0**-24 * float(np.max(np.abs(expected[inside])))
    assert worst <= max(TOLERANCE_DPS, ulp_bound), f"largest difference {worst:.2e} deg/s"
    lib = lib_for_hypothesis.lib
    fixed = ctypes.create_string_buffer(lib_for_hypothesis.fixed_size)
    assert lib.ce_fixed_from(fixed, fw._set) == 0
    out = ctypes.c_int32()
    for r, e, o in zip(raw[::7].astype(np.int32).tolist(), expected[::7].tolist(), expected_oos[::7].tolist(),
                       strict=True):  # fmt: skip
        assert lib.ce_fixed_eval(fixed, r, ctypes.byref(out)) == o
        assert abs(out.value / 65536.0 - e) < 1e-3
