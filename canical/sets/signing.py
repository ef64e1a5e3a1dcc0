"""Ed25519 signatures of coefficient sets: who made a set, for which sensor, which version of it.

Why: a CRC proves a set was not damaged, never who wrote it; anyone who can write a file in
``/etc/canical`` could change what a vehicle believes about its own motion. The calibration lab
signs a set with its private key; the vehicle checks the signature against the lab's public keys
it trusts. A signature covers the set's canonical content (the bytes its CRC covers, so it does
not depend on YAML formatting), the sensor it is for (a set cannot be moved to another sensor)
and a version that only grows (an older signed set cannot replace a newer one: rollback). The
cryptography is PyNaCl's (libsodium), never canical's own.

The signature sits in the set file beside the content, not in it: the CRC of a signed set is the
CRC of the same set unsigned, and unsigned sets load as they always did.
"""

from __future__ import annotations

import base64
import binascii
import hashlib
import json
from dataclasses import dataclass
from typing import Any

import nacl.exceptions
import nacl.signing

from canical.errors import CanicalError

#: The top-level key of a set file the signature is stored under (outside the CRC's content).
SIGNATURE_KEY = "signature"
#: Signed before everything else: a signature over a set can never be read as one over other data.
DOMAIN = b"canical signed set v1\n"
SIGNATURE_BYTES = 64
#: A key id is the first 8 bytes of the public key's SHA-256, in hex: enough to name a key in a log.
KEY_ID_BYTES = 8
#: Versions fit a signed 64-bit counter (a device's anti-rollback counter can hold them).
MAX_VERSION = 2**63 - 1


@dataclass(frozen=True)
class SignatureRecord:
    """One signature: by which key, of which version of the set, for which sensor."""

    key_id: str
    version: int
    sensor_id: str
    signature: bytes

    def to_dict(self) -> dict[str, Any]:
        """The record as the set file holds it (the signature in base64)."""
        return {"key_id": self.key_id, "version": self.version, "sensor": self.sensor_id,
                "ed25519": base64.b64encode(self.signature).decode("ascii")}


@dataclass(frozen=True)
class SignedContent:
    """What a set file says of its origin: its record (None: unsigned, or ``problem`` says why it
    cannot be read) and the canonical bytes a signature must cover, with the set's own sensor."""

    record: SignatureRecord | None
    canonical: bytes
    sensor_id: str
    problem: str | None = None


@dataclass(frozen=True)
class TrustedKey:
    """A public key a verifier trusts, and where it was read from (to name it in messages)."""

    public: bytes
    origin: str

    @property
    def key_id(self) -> str:
        return key_id_of(self.public)


def key_id_of(public: bytes) -> str:
    return hashlib.sha256(public).digest()[:KEY_ID_BYTES].hex()


def new_seed() -> bytes:
    """A fresh private key (its 32-byte seed), from the operating system's randomness."""
    return bytes(nacl.signing.SigningKey.generate().encode())


def public_of(seed: bytes) -> bytes:
    return bytes(nacl.signing.SigningKey(seed).verify_key.encode())


def signed_message(canonical: bytes, version: int, sensor_id: str) -> bytes:
    """The bytes signed: the domain, the version and sensor (as canonical JSON: no ambiguity
    between the header and the content), then the set's canonical content."""
    header = json.dumps({"sensor": sensor_id, "version": version}, sort_keys=True, separators=(",", ":"))
    return DOMAIN + header.encode() + b"\n" + canonical


def sign(seed: bytes, canonical: bytes, version: int, sensor_id: str) -> SignatureRecord:
    """Sign a set's canonical content as ``version`` of the set for ``sensor_id``."""
    if not 0 <= version <= MAX_VERSION:
        raise CanicalError(f"version {version} out of range 0..{MAX_VERSION}")
    key = nacl.signing.SigningKey(seed)
    signature = key.sign(signed_message(canonical, version, sensor_id)).signature
    return SignatureRecord(key_id_of(bytes(key.verify_key.encode())), version, sensor_id, bytes(signature))


def signed_content(content: dict[str, Any], canonical: bytes, sensor_id: str) -> SignedContent:
    """The origin a set's parsed content claims; a malformed record is kept as a ``problem``
    (an unsigned reader does not need it; a verifier refuses it)."""
    value = content.get(SIGNATURE_KEY)
    if value is None:
        return SignedContent(None, canonical, sensor_id)
    try:
        return SignedContent(record_from_file(value), canonical, sensor_id)
    except ValueError as exc:
        return SignedContent(None, canonical, sensor_id, problem=f"signature: {exc}")


def record_from_file(value: Any) -> SignatureRecord:
    """Parse the ``signature`` mapping of a set file; any defect is a ValueError saying which."""
    if not isinstance(value, dict) or set(value) != {"key_id", "version", "sensor", "ed25519"}:
        raise ValueError("must be a mapping of key_id, version, sensor and ed25519")
    key_id, version, sensor, encoded = value["key_id"], value["version"], value["sensor"], value["ed25519"]
    if not isinstance(key_id, str) or len(key_id) != 2 * KEY_ID_BYTES:
        raise ValueError(f"key_id must be {2 * KEY_ID_BYTES} hexadecimal digits")
    if not isinstance(version, int) or isinstance(version, bool) or not 0 <= version <= MAX_VERSION:
        raise ValueError(f"version must be an integer 0..{MAX_VERSION}")
    if not isinstance(sensor, str) or not sensor:
        raise ValueError("sensor must be a non-empty string")
    if not isinstance(encoded, str):
        raise ValueError("ed25519 must be base64 text")
    try:
        signature = base64.b64decode(encoded.encode("ascii"), validate=True)
    except (binascii.Error, UnicodeEncodeError):
        raise ValueError("ed25519 is not base64") from None
    if len(signature) != SIGNATURE_BYTES:
        raise ValueError(f"ed25519 is {len(signature)} bytes, not {SIGNATURE_BYTES} (truncated?)")
    return SignatureRecord(key_id, version, sensor, signature)


def verify(signed: SignedContent, trusted: tuple[TrustedKey, ...], source: str) -> SignatureRecord:
    """The set's signature record if a trusted key signed this content for this sensor; otherwise
    one :class:`CanicalError` line saying why not."""
    if signed.problem is not None:
        raise CanicalError(f"{source}: {signed.problem}")
    record = signed.record
    if record is None:
        raise CanicalError(f"{source}: not signed (a signature from a trusted key is required)")
    if record.sensor_id != signed.sensor_id:
        raise CanicalError(f"{source}: signed for sensor {record.sensor_id}, the set is for sensor "
                           f"{signed.sensor_id}")
    key = next((k for k in trusted if k.key_id == record.key_id), None)
    if key is None:
        raise CanicalError(f"{source}: signed by key {record.key_id}, which is not trusted")
    message = signed_message(signed.canonical, record.version, record.sensor_id)
    try:
        nacl.signing.VerifyKey(key.public).verify(message, record.signature)
    except nacl.exceptions.BadSignatureError:
        raise CanicalError(f"{source}: signature by key {record.key_id} ({key.origin}) does not match "
                           "the content: changed after signing") from None
    return record


def check_not_older(record: SignatureRecord, running: int | None, source: str) -> None:
    """Refuse a set older than the one it would replace (``running``: its version, None: none
    signed): an attacker must not bring back a set the lab has since replaced."""
    if running is not None and record.version < running:
        raise CanicalError(f"{source}: version {record.version} is older than the running set's "
                           f"version {running}: a rollback")
