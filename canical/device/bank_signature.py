"""A set's signature as a device bank carries it, and the check a device makes before activating.

Why its own format: a bank is bytes, not YAML. The "Signature" sub-index of a bank holds the
signature record of :mod:`canical.sets.signing` packed in 80 bytes (version as UNSIGNED64
little-endian, the key id's 8 bytes, the Ed25519 signature's 64) so a firmware reads it with no
parser. The signed message is the very one the lab signs (:func:`canical.sets.signing.signed_message`)
over the bank's content, for the device's own sensor id (its serial number): a set signed for
another sensor does not verify on this one. An IMU set's signature sits on its coupling bank and
covers the whole IMU set, whose canonical bytes the device rebuilds from the coupling content and
the three axis contents (:func:`joined_imu_canonical`: "axes" sorts before every other key).
"""

from __future__ import annotations

import os
import struct
from collections.abc import Sequence
from dataclasses import dataclass

import nacl.exceptions
import nacl.signing

from canical.errors import CanicalError
from canical.frames.imu_dictionary import (
    BANK_SIGNATURE_BYTES,
    SIGNATURE_KEY_ID_BYTES,
    SIGNATURE_VERSION_BYTES,
    TRUST_KEY_BYTES,
)
from canical.sets.signed_file import read_set_file
from canical.sets.signing import SignatureRecord, SignedContent, TrustedKey, key_id_of, signed_message, verify


@dataclass(frozen=True)
class BankSignature:
    """A bank's signature: the set's version, the signing key's id and the Ed25519 signature."""

    version: int
    key_id: bytes
    signature: bytes

    def pack(self) -> bytes:
        """The 80 bytes of the bank's "Signature" sub-index."""
        return struct.pack("<Q", self.version) + self.key_id + self.signature

    def record(self, sensor_id: str) -> SignatureRecord:
        """The record a set file carries for this signature (the sensor: the set's own)."""
        return SignatureRecord(self.key_id.hex(), self.version, sensor_id, self.signature)


def from_record(record: SignatureRecord) -> BankSignature:
    """A set file's signature record as a bank carries it (its sensor is the device's)."""
    return BankSignature(record.version, bytes.fromhex(record.key_id), record.signature)


def bank_signatures(paths: Sequence[str | os.PathLike[str]]) -> dict[str, bytes]:
    """The signatures set files carry, as banks carry them: by axis, ``"imu"`` for an IMU set's
    (written to its coupling bank). A device with a trust key refuses to activate a set without."""
    out = {}
    for path in paths:
        checked = read_set_file(path)
        record = checked.signed.record
        if record is not None:
            key = "imu" if checked.single is None else checked.single.axis
            out[key] = from_record(record).pack()
    return out


def unpack(data: bytes, where: str) -> BankSignature:
    """The signature a bank's "Signature" bytes hold; one CanicalError line when they cannot be one
    (empty: unsigned; another length: truncated or garbage)."""
    if not data:
        raise CanicalError(f"{where}: not signed (the device's trust key requires a signature)")
    if len(data) != BANK_SIGNATURE_BYTES:
        raise CanicalError(f"{where}: signature is {len(data)} bytes, not {BANK_SIGNATURE_BYTES} "
                           "(truncated or garbage)")
    version = struct.unpack("<Q", data[:SIGNATURE_VERSION_BYTES])[0]
    key_end = SIGNATURE_VERSION_BYTES + SIGNATURE_KEY_ID_BYTES
    return BankSignature(version, data[SIGNATURE_VERSION_BYTES:key_end], data[key_end:])


def record_of(data: bytes, sensor_id: str, where: str) -> SignatureRecord | None:
    """The signature record a bank's "Signature" bytes make for a set of ``sensor_id`` (None:
    empty, unsigned); one CanicalError line when they cannot be one."""
    return None if not data else unpack(data, where).record(sensor_id)


def verify_pulled(data: bytes, canonical: bytes, sensor_id: str, trusted: tuple[TrustedKey, ...],
                  where: str) -> SignatureRecord:
    """The record of a set read from a device (its canonical content, the bank's "Signature"
    bytes) if a trusted key signed it for its sensor; else one CanicalError line: what a set file
    gets (:func:`canical.sets.signing.verify`), for the bytes the device holds."""
    return verify(SignedContent(record_of(data, sensor_id, where), canonical, sensor_id), trusted, where)


def joined_imu_canonical(envelope: bytes, axes: tuple[bytes, ...]) -> bytes:
    """The canonical bytes of the whole IMU set from its coupling bank's content (the IMU set
    without its axes) and its x, y, z axis banks' contents: canonical JSON sorts "axes" first, so
    the whole set is ``{"axes":{"x":X,"y":Y,"z":Z},`` then the envelope without its ``{``."""
    x, y, z = axes
    return b'{"axes":{"x":' + x + b',"y":' + y + b',"z":' + z + b"}," + envelope[1:]


def verify_bank(data: bytes, canonical: bytes, sensor_id: str, trust_key: bytes, min_version: int,
                where: str) -> int:
    """The version of a bank signed by ``trust_key`` over ``canonical`` for ``sensor_id``, not older
    than ``min_version`` (the device's anti-rollback counter); else one CanicalError line."""
    if len(trust_key) != TRUST_KEY_BYTES:
        raise CanicalError(f"{where}: the device's trust key is {len(trust_key)} bytes, "
                           f"not {TRUST_KEY_BYTES}")
    sig = unpack(data, where)
    expected = key_id_of(trust_key)
    if sig.key_id.hex() != expected:
        raise CanicalError(f"{where}: signed by key {sig.key_id.hex()}, not by the device's trust key "
                           f"{expected}")
    try:
        nacl.signing.VerifyKey(trust_key).verify(signed_message(canonical, sig.version, sensor_id),
                                                  sig.signature)
    except nacl.exceptions.BadSignatureError:
        raise CanicalError(f"{where}: signature does not match the content for sensor {sensor_id} "
                           "(changed after signing, or signed for another sensor)") from None
    if sig.version < min_version:
        raise CanicalError(f"{where}: version {sig.version} is older than version {min_version} the "
                           "device has run: a rollback")
    return int(sig.version)
