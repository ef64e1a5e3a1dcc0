"""A coefficient set as the bytes of a device bank, and back.

The bank's Content is exactly the bytes the set's CRC covers: the canonical
JSON of :func:`canical.sets.coefficient_file.canonical_bytes`. So the bank's CRC32
*is* the set's identifier, a device validates a bank with one CRC over what it
received plus the same field checks a file gets, and an upload can be turned
back into a YAML file that is byte-for-byte the same set. Non-canonical JSON
(other key order, spacing, float spelling) is refused: its CRC would not be the
set's identifier.

An IMU set travels as its three axes (one axis bank each, as above) and a coupling
bank: the IMU set's content without its axes, canonical JSON too, with its own CRC32
and the IMU set's id (the CRC32 of the whole IMU set). The matrix stays the JSON
numbers the IMU set's CRC covers (not REAL32 objects): that is what lets the device
check the coupling belongs to the axes beside it, and a pull give back the very set.
"""

from __future__ import annotations

import json
import zlib
from dataclasses import dataclass
from typing import Any

import numpy as np

from canical.errors import CanicalError
from canical.sets.coefficient_file import canonical_bytes, content_crc, from_content
from canical.sets.coefficients import SCHEMA_VERSION, CoefficientSet, finite
from canical.sets.imu_set import IMU_SET_KIND, ImuSet, Matrix, as_matrix, check_coupling, imu_set_crc
from canical.sets.imu_set import from_content as imu_from_content


def encode_set(cset: CoefficientSet) -> tuple[bytes, int]:
    """(bank content, CRC32) for a set; the CRC equals :func:`canical.sets.coefficient_file.set_crc`."""
    content = canonical_bytes(cset.to_dict())
    return content, zlib.crc32(content) & 0xFFFFFFFF


def decode_set(content: bytes, crc: int, source: str) -> CoefficientSet:
    """Validate bank bytes against their CRC and every field, and build the set.

    Raises :class:`CanicalError` with one line naming ``source`` and the problem.
    """
    parsed = _canonical_object(content, crc, source, "coefficient-set")
    parsed["crc32"] = f"0x{crc:08x}"
    return from_content(parsed, source)


def _no_constant(name: str) -> float:
    """NaN and Infinity are not JSON: a bank holding them is refused, not parsed."""
    raise ValueError(f"{name} is not a JSON number")


# ---------------------------------------------------------------------------------------------
# The coupling bank: an IMU set without its axes
# ---------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class CouplingPayload:
    """What a coupling bank holds: the IMU set's content without its axes (the coupling matrix,
    its standard errors, sensor, created, fit) as canonical JSON, that content's CRC32, and the
    CRC32 of the whole IMU set (its id), which the three axis banks and this content must make."""

    content: bytes
    crc: int
    imu_set_id: int


def encode_coupling(imu: ImuSet) -> CouplingPayload:
    """The coupling bank of an IMU set (its axes go to the axis banks, one set each)."""
    envelope = {k: v for k, v in imu.to_dict().items() if k != "axes"}
    content = canonical_bytes(envelope)
    return CouplingPayload(content, zlib.crc32(content) & 0xFFFFFFFF, imu_set_crc(imu))


@dataclass(frozen=True)
class CouplingContent:
    """A coupling bank's validated content: whose it is, the matrix, and the parsed content as its
    CRC covers it (kept whole: joined with three axis sets it must give the IMU set's id)."""

    sensor_id: str
    matrix: Matrix
    fields: dict[str, Any]


def decode_coupling(content: bytes, crc: int, source: str) -> CouplingContent:
    """Validate coupling-bank bytes on their own (CRC, canonical JSON, kind, schema, sensor id,
    a 3×3 matrix that passes :func:`~canical.sets.imu_set.check_coupling`); the parsed content.

    Whether the coupling belongs to the axes beside it is :func:`join_imu_set`'s question.
    """
    parsed = _canonical_object(content, crc, source, "IMU-set coupling")
    if parsed.get("kind") != IMU_SET_KIND:
        raise CanicalError(f"{source}: not an IMU set's coupling (kind {parsed.get('kind')!r})")
    if "axes" in parsed:
        raise CanicalError(f"{source}: holds axes: a coupling bank holds the IMU set without them")
    if parsed.get("schema") != SCHEMA_VERSION:
        raise CanicalError(f"{source}: schema {parsed.get('schema')!r} not supported")
    sensor = parsed.get("sensor")
    if not isinstance(sensor, dict) or not isinstance(sensor.get("id"), str) or not sensor["id"]:
        raise CanicalError(f"{source}: sensor.id must be a non-empty string")
    coupling = parsed.get("coupling")
    matrix = coupling.get("matrix") if isinstance(coupling, dict) else None
    ok = (isinstance(matrix, list) and len(matrix) == 3
          and all(isinstance(r, list) and len(r) == 3 and all(finite(v) for v in r) for r in matrix))
    if not ok:
        raise CanicalError(f"{source}: coupling.matrix must be 3 rows of 3 finite numbers")
    check_coupling(np.asarray(matrix, dtype=float), source)
    return CouplingContent(sensor["id"], as_matrix(matrix), parsed)


def join_imu_set(envelope: CouplingContent, axes: tuple[CoefficientSet, ...], imu_set_id: int,
                 source: str) -> ImuSet:
    """The IMU set a coupling bank's content and three axis sets make, if its id is ``imu_set_id``.

    Refused in one line when the axes are not the ones the coupling was fitted with: the coupling
    is only right with the per-axis models whose scales fixed its diagonal.
    """
    content = {**envelope.fields, "axes": {c.axis: c.to_dict() for c in axes}}
    actual = content_crc(content)
    if actual != imu_set_id:
        ids = ", ".join(f"{c.axis} 0x{content_crc(c.to_dict()):08x}" for c in axes)
        raise CanicalError(f"{source} belongs to IMU set 0x{imu_set_id:08x}; with the axes selected "
                           f"({ids}) it would make 0x{actual:08x}: push the whole IMU set")
    return imu_from_content({**content, "crc32": f"0x{imu_set_id:08x}"}, source)


def _canonical_object(content: bytes, crc: int, source: str, what: str) -> dict[str, Any]:
    actual = zlib.crc32(content) & 0xFFFFFFFF
    if actual != crc:
        raise CanicalError(f"{source}: CRC mismatch (declared 0x{crc:08x}, content gives 0x{actual:08x})")
    try:
        parsed = json.loads(content.decode("utf-8"), parse_constant=_no_constant)
    except (UnicodeDecodeError, ValueError) as exc:
        raise CanicalError(f"{source}: content is not {what} JSON ({exc})") from None
    if not isinstance(parsed, dict):
        raise CanicalError(f"{source}: content is not {what} JSON (expected an object)")
    try:
        canonical = canonical_bytes(parsed)
    except ValueError:  # a number beyond float range (1e999): never written by canical
        canonical = b""
    if canonical != content:
        raise CanicalError(f"{source}: content is not in canonical form (its CRC is not the set's id)")
    return parsed
