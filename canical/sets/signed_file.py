"""Set files with their signatures: read a set with the origin it claims, sign a set file.

Why apart from the loaders: a set's loader checks what a set is (CRC, fields, finite outputs);
this module adds where it came from, for every kind of set file (single-axis and IMU sets), so
the commands and the daemon read a set and its signature in one step and verify it against the
keys they trust (:mod:`canical.sets.signing`). Signing rewrites the file with the signature
beside the content; the content's bytes, and so its CRC, are unchanged.
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from typing import Any

import yaml

from canical.errors import CanicalError
from canical.files.atomic_file import write_text_atomic
from canical.files.yaml_text import parse_yaml
from canical.sets import coefficient_file, imu_set
from canical.sets.coefficients import CoefficientSet
from canical.sets.imu_set import IMU_SET_KIND, ImuSet
from canical.sets.signing import (
    SIGNATURE_KEY,
    SignatureRecord,
    SignedContent,
    TrustedKey,
    check_not_older,
    sign,
    signed_content,
    verify,
)

__all__ = ["SetFile", "load_imu", "load_set", "next_version", "read_set_file", "sign_file", "sign_text",
           "verified", "with_signature"]


@dataclass(frozen=True)
class SetFile:
    """A validated set file of either kind (``imu`` for an IMU set, else ``single``) and its origin."""

    single: CoefficientSet | None
    imu: ImuSet | None
    signed: SignedContent

    @property
    def crc(self) -> int:
        if self.imu is not None:
            return imu_set.imu_set_crc(self.imu)
        assert self.single is not None
        return coefficient_file.set_crc(self.single)


def _content(path: str | os.PathLike[str]) -> tuple[Any, str]:
    source = str(path)
    return parse_yaml(coefficient_file.read_text(path, "coefficient file"), source), source


def read_set_file(path: str | os.PathLike[str]) -> SetFile:
    """Read and fully validate a set file of either kind, with the signature it carries."""
    content, source = _content(path)
    return _validated(content, source)


def _validated(content: Any, source: str) -> SetFile:
    """Parsed set content of either kind, validated as its kind, with its origin."""
    if isinstance(content, dict) and content.get("kind") == IMU_SET_KIND:
        imu = imu_set.from_content(content, source)
        return SetFile(None, imu, _origin(content, imu.sensor_id))
    single = coefficient_file.from_content(content, source)
    return SetFile(single, None, _origin(content, single.sensor_id))


def load_set(path: str | os.PathLike[str]) -> tuple[CoefficientSet, SignedContent]:
    """A single-axis set and its origin (the loader's checks, then the signature's record)."""
    content, source = _content(path)
    cset = coefficient_file.from_content(content, source)
    return cset, _origin(content, cset.sensor_id)


def load_imu(path: str | os.PathLike[str]) -> tuple[ImuSet, SignedContent]:
    """An IMU set and its origin."""
    content, source = _content(path)
    imu = imu_set.from_content(content, source)
    return imu, _origin(content, imu.sensor_id)


def _origin(content: dict[str, Any], sensor_id: str) -> SignedContent:
    return signed_content(content, coefficient_file.canonical_bytes(content), sensor_id)


def verified(signed: SignedContent, trusted: tuple[TrustedKey, ...], running: int | None,
             source: str) -> SignatureRecord:
    """The record of a set signed by a trusted key for its sensor, not older than ``running``;
    else one CanicalError line (unsigned, untrusted, tampered, another sensor, rollback)."""
    record = verify(signed, trusted, source)
    check_not_older(record, running, source)
    return record


def sign_file(path: str | os.PathLike[str], seed: bytes, version: int | None) -> SignatureRecord:
    """Sign a set file in place as ``version`` (None: one more than the version it carries, or 1).

    The file is validated first (a damaged set is never signed) and rewritten atomically with the
    signature before the CRC; any signature it had is replaced.
    """
    text = coefficient_file.read_text(path, "coefficient file")
    signed, record = sign_text(text, str(path), seed, version)
    write_text_atomic(path, signed)
    return record


def sign_text(text: str, source: str, seed: bytes, version: int | None) -> tuple[str, SignatureRecord]:
    """A set's text with its signature as ``version`` (None: one more than the text's, or 1)."""
    content = parse_yaml(text, source)
    previous = _validated(content, source).signed  # a damaged set is never signed
    if version is None:
        version = 1 if previous.record is None else previous.record.version + 1
    record = sign(seed, previous.canonical, version, previous.sensor_id)
    return _with_record(content, source, record), record


def with_signature(text: str, source: str, record: SignatureRecord) -> str:
    """A set's text with ``record`` as its signature (a signature read from a device's bank):
    written beside the content, so the content and its CRC are unchanged."""
    content = parse_yaml(text, source)
    _validated(content, source)  # a damaged set is never given a signature
    return _with_record(content, source, record)


def _with_record(content: dict[str, Any], source: str, record: SignatureRecord) -> str:
    body = {k: v for k, v in content.items() if k not in (SIGNATURE_KEY, "crc32")}
    signed = yaml.safe_dump({**body, SIGNATURE_KEY: record.to_dict(), "crc32": content["crc32"]},
                            sort_keys=False, default_flow_style=None, width=100)
    if _validated(parse_yaml(signed, source), source).signed.record != record:
        raise CanicalError(f"{source}: the signed set does not read back as signed")  # never written
    return signed


def next_version(path: str | os.PathLike[str]) -> int:
    """The version a new set replacing ``path`` is signed as: one more than the file's, else 1
    (no file, or not a signed set)."""
    try:
        record = read_set_file(path).signed.record
    except CanicalError:
        return 1
    return 1 if record is None else record.version + 1

