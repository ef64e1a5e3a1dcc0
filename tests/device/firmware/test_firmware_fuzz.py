"""The firmware's C evaluator fuzzed under AddressSanitizer and UBSan: structured malformed banks and
random mutations are all refused, never read out of bounds, and refused as canical refuses them."""

from __future__ import annotations

import copy
import json
import random
import struct
import subprocess
import zlib
from pathlib import Path

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from support.firmware_build import (
    CE_MAX_SEGMENTS,
    CODES,
    RATED,
    load_code,
    python_verdict,
    seeds,
)
from support.firmware_cases import (
    ALL_TERMS,
    AXIS,
    CHANNELS,
    MODELS,
    SERIAL,
)

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

