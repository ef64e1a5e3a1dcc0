"""A coefficient set as the bytes of a device bank, and back.

The bank's Content is exactly the bytes the set's CRC covers: the canonical
JSON of :func:`canical.sets.coefficient_file.canonical_bytes`. So the bank's CRC32
*is* the set's identifier, a device validates a bank with one CRC over what it
received plus the same field checks a file gets, and an upload can be turned
back into a YAML file that is byte-for-byte the same set. Non-canonical JSON
(other key order, spacing, float spelling) is refused: its CRC would not be the
set's identifier.
"""

from __future__ import annotations

import json
import zlib

from canical.errors import CanicalError
from canical.sets.coefficient_file import canonical_bytes, from_content
from canical.sets.coefficients import CoefficientSet


def encode_set(cset: CoefficientSet) -> tuple[bytes, int]:
    """(bank content, CRC32) for a set; the CRC equals :func:`canical.sets.coefficient_file.set_crc`."""
    content = canonical_bytes(cset.to_dict())
    return content, zlib.crc32(content) & 0xFFFFFFFF


def decode_set(content: bytes, crc: int, source: str) -> CoefficientSet:
    """Validate bank bytes against their CRC and every field, and build the set.

    Raises :class:`CanicalError` with one line naming ``source`` and the problem.
    """
    actual = zlib.crc32(content) & 0xFFFFFFFF
    if actual != crc:
        raise CanicalError(f"{source}: CRC mismatch (declared 0x{crc:08x}, content gives 0x{actual:08x})")
    try:
        parsed = json.loads(content.decode("utf-8"), parse_constant=_no_constant)
    except (UnicodeDecodeError, ValueError) as exc:
        raise CanicalError(f"{source}: content is not coefficient-set JSON ({exc})") from None
    if not isinstance(parsed, dict):
        raise CanicalError(f"{source}: content is not a coefficient set (expected a JSON object)")
    try:
        canonical = canonical_bytes(parsed)
    except ValueError:  # a number beyond float range (1e999): never written by canical
        canonical = b""
    if canonical != content:
        raise CanicalError(f"{source}: content is not in canonical form (its CRC is not the set's id)")
    parsed["crc32"] = f"0x{crc:08x}"
    return from_content(parsed, source)


def _no_constant(name: str) -> float:
    """NaN and Infinity are not JSON: a bank holding them is refused, not parsed."""
    raise ValueError(f"{name} is not a JSON number")
