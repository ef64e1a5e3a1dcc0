"""Coefficient sets as YAML files, with a CRC32 over their canonical content.

The CRC is computed over a canonical JSON rendering of everything but the CRC
itself (sorted keys, no spaces, shortest round-trip floats), so it does not
depend on YAML formatting and a device can recompute it over the same bytes. A
lab's signature (:mod:`canical.sets.signing`) sits beside the content, outside
those bytes: it covers them, and a signed set keeps the CRC it had unsigned.
Loading checks every field and refuses a damaged or hand-edited file with one
line naming what is wrong.
"""

from __future__ import annotations

import json
import os
import zlib
from typing import Any

import yaml

from canical.errors import CanicalError
from canical.files.atomic_file import write_text_atomic
from canical.files.yaml_text import parse_yaml
from canical.sets.coefficients import DEFAULT_RAW_UNITS, SCHEMA_VERSION, CoefficientSet
from canical.sets.finite_outputs import check_finite_outputs
from canical.sets.set_model import FailFn, finite, model_from_dict
from canical.sets.signing import SIGNATURE_KEY
from canical.sets.terms import term_from_file

__all__ = ["FailFn", "canonical_bytes", "content_crc", "dumps", "from_content", "load", "loads", "read_text",
           "save", "set_crc"]


def canonical_bytes(content: dict[str, Any]) -> bytes:
    """The bytes the CRC (and a signature) covers: the content without ``crc32`` and without its
    signature, as canonical JSON."""
    body = {k: v for k, v in content.items() if k not in ("crc32", SIGNATURE_KEY)}
    return json.dumps(body, sort_keys=True, separators=(",", ":"), allow_nan=False).encode()


def content_crc(content: dict[str, Any]) -> int:
    return zlib.crc32(canonical_bytes(content)) & 0xFFFFFFFF


def set_crc(cset: CoefficientSet) -> int:
    """The set's CRC32, which also serves as its identifier on the bus."""
    return content_crc(cset.to_dict())


def dumps(cset: CoefficientSet) -> str:
    """YAML text of a set, CRC last."""
    content = cset.to_dict()
    content["crc32"] = f"0x{content_crc(content):08x}"
    return yaml.safe_dump(content, sort_keys=False, default_flow_style=None, width=100)


def save(path: str | os.PathLike[str], cset: CoefficientSet) -> None:
    """Write a set atomically (validated first, so no bad set is ever written)."""
    text = dumps(cset)
    loads(text, str(path))
    write_text_atomic(path, text)


def read_text(path: str | os.PathLike[str], what: str) -> str:
    """A set file's text; missing or unreadable is one line naming the file and ``what`` it is."""
    name = str(path)
    try:
        with open(path, encoding="utf-8") as handle:
            return handle.read()
    except FileNotFoundError:
        raise CanicalError(f"{name}: {what} not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CanicalError(f"{name}: cannot read {what} ({exc})") from None


def load(path: str | os.PathLike[str]) -> CoefficientSet:
    return loads(read_text(path, "coefficient file"), str(path))


def loads(text: str, source: str = "<coefficients>") -> CoefficientSet:
    """Parse and fully validate a set; any defect raises one :class:`CanicalError` line."""
    return from_content(parse_yaml(text, source), source)


def from_content(content: Any, source: str) -> CoefficientSet:
    """Validate parsed content (from YAML or from a device) and build the set."""

    def fail(msg: str) -> CanicalError:
        return CanicalError(f"{source}: {msg}")

    if not isinstance(content, dict):
        raise fail("not a coefficient set (expected a mapping at the top level)")
    if content.get("kind") == "imu-set":
        raise fail("an IMU set (three axes and their coupling), not a single-axis coefficient set")
    schema = content.get("schema")
    if schema != SCHEMA_VERSION:
        raise fail(f"schema {schema!r} not supported (this canical reads schema {SCHEMA_VERSION})")
    crc_text = content.get("crc32")
    if not isinstance(crc_text, str):
        raise fail("crc32 missing")
    try:
        crc = int(crc_text, 16)
    except ValueError:
        raise fail(f"crc32 {crc_text!r} is not hexadecimal") from None
    try:
        actual = content_crc(content)
    except (TypeError, ValueError) as exc:
        raise fail(f"content cannot be checked ({exc})") from None
    if crc != actual:
        raise fail(f"CRC mismatch (file says 0x{crc:08x}, content gives 0x{actual:08x}): damaged or edited")
    sensor = _mapping(content, "sensor", fail)
    units = _mapping(content, "units", fail)
    model = _mapping(content, "model", fail)
    v0 = content.get("v0")
    if not finite(v0):
        raise fail("v0 must be a finite number")
    for key in ("id", "axis"):
        if not isinstance(sensor.get(key), str) or not sensor.get(key):
            raise fail(f"sensor.{key} must be a non-empty string")
    typed_model = model_from_dict(model, fail)
    terms = content.get("terms", [])
    if not isinstance(terms, list):
        raise fail("terms must be a list")
    checked = []
    for i, term in enumerate(terms):
        if not isinstance(term, dict):
            raise fail(f"terms[{i}] must be a mapping")
        try:
            checked.append(term_from_file(term, f"terms[{i}]"))
        except ValueError as exc:
            raise fail(str(exc)) from None
    if terms and not typed_model.kind.piecewise:
        raise fail("effect terms need a segmented model")
    fit = content.get("fit", {})
    if not isinstance(fit, dict):
        raise fail("fit must be a mapping")
    cset = CoefficientSet(
        sensor_id=sensor["id"],
        axis=sensor["axis"],
        v0=float(v0),
        model=typed_model,
        terms=tuple(checked),
        fit=fit,
        created=str(content.get("created", "")),
        raw_units=str(units.get("raw", DEFAULT_RAW_UNITS)),
        rate_units=str(units.get("rate", "deg/s")),
        schema=schema,
    )
    lo, hi = cset.span_raw
    unbounded = check_finite_outputs(cset.rate_model(), cset.terms, (lo - cset.v0, hi - cset.v0))
    if unbounded is not None:
        raise fail(unbounded.message())
    return cset


def _mapping(content: dict[str, Any], key: str, fail: FailFn) -> dict[str, Any]:
    value = content.get(key)
    if not isinstance(value, dict):
        raise fail(f"{key} missing or not a mapping")
    return value
