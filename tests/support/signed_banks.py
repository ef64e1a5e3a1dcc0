"""Signed banks for the device tests: the lab's and a stranger's keys, and every way a bank can fail
to carry the lab's signature (unsigned, another key, tampered with or without its CRC recomputed,
for another sensor, rolled back, a truncated or garbage signature), as the bytes a push writes.

Why one place: the emulated IMU (Python) and the firmware's C library must agree on every case,
so both are given the very same bytes and asked the same question.
"""

from __future__ import annotations

import json
import struct
import zlib
from dataclasses import dataclass, replace
from typing import Any

from canical.device.bank_payload import encode_coupling, encode_set
from canical.device.bank_signature import from_record
from canical.sets.coefficient_file import canonical_bytes
from canical.sets.coefficients import CoefficientSet
from canical.sets.imu_set import ImuSet
from canical.sets.signing import public_of, sign
from support.imu_fixtures import SENSOR

LAB_SEED = bytes(range(32))
STRANGER_SEED = bytes(range(100, 132))
LAB_PUBLIC = public_of(LAB_SEED)
#: The device's anti-rollback counter in the cases: the previous set was version 5.
COUNTER = 5
VERSION = 7
OLD_VERSION = 4


def bank_signature(seed: bytes, content: bytes, version: int, sensor: str = SENSOR) -> bytes:
    """The 80 bytes of a bank's "Signature" for ``content`` signed with ``seed``."""
    return from_record(sign(seed, content, version, sensor)).pack()


def imu_canonical(imu: ImuSet) -> bytes:
    """The bytes an IMU set's signature covers (the file's canonical content)."""
    return canonical_bytes(imu.to_dict())


def imu_signature(seed: bytes, imu: ImuSet, version: int, sensor: str = SENSOR) -> bytes:
    return bank_signature(seed, imu_canonical(imu), version, sensor)


def flip_one_bit(content: bytes) -> bytes:
    """The set's canonical content with the lowest bit of its first model coefficient flipped."""
    parsed = json.loads(content)
    _flip_first_float(parsed["model"])
    return canonical_bytes(parsed)


def _flip_first_float(node: Any) -> bool:
    items = node.items() if isinstance(node, dict) else enumerate(node) if isinstance(node, list) else ()
    for key, value in items:
        if isinstance(value, float) and value != 0.0:
            bits = struct.unpack("<Q", struct.pack("<d", value))[0] ^ 1
            node[key] = struct.unpack("<d", struct.pack("<Q", bits))[0]
            return True
        if _flip_first_float(value):
            return True
    return False


def crc(content: bytes) -> int:
    return zlib.crc32(content) & 0xFFFFFFFF


@dataclass(frozen=True)
class BankCase:
    """One axis bank as a push writes it, and the words the refusal must hold (None: adopted)."""

    name: str
    content: bytes
    crc: int
    signature: bytes
    refusal: str | None


def axis_cases(cset: CoefficientSet) -> list[BankCase]:
    """Every case for one axis set: refused ones, then the valid one."""
    content, good_crc = encode_set(cset)
    tampered = flip_one_bit(content)
    valid = bank_signature(LAB_SEED, content, VERSION)
    return [
        BankCase("unsigned", content, good_crc, b"", "not signed"),
        BankCase("untrusted key", content, good_crc, bank_signature(STRANGER_SEED, content, VERSION),
                 "not by the device's trust key"),
        BankCase("tampered, CRC kept", tampered, good_crc, valid, "CRC mismatch"),
        BankCase("tampered, CRC recomputed", tampered, crc(tampered), valid, "does not match the content"),
        BankCase("another sensor", content, good_crc, bank_signature(LAB_SEED, content, VERSION, "4712"),
                 "does not match the content"),
        BankCase("rolled back", content, good_crc, bank_signature(LAB_SEED, content, OLD_VERSION),
                 "a rollback"),
        BankCase("truncated signature", content, good_crc, valid[:40], "40 bytes, not 80"),
        BankCase("garbage signature", content, good_crc, bytes(range(80)), "not by the device's trust key"),
        BankCase("garbage in the signature bytes", content, good_crc, valid[:16] + bytes(64),
                 "does not match the content"),
        BankCase("valid", content, good_crc, valid, None),
    ]


@dataclass(frozen=True)
class ImuCase:
    """An IMU set as a push writes it: three axis contents, the coupling bank and its signature."""

    name: str
    axes: tuple[bytes, bytes, bytes]
    coupling: bytes
    coupling_crc: int
    imu_set_id: int
    signature: bytes
    refusal: str | None


def imu_cases(imu: ImuSet) -> list[ImuCase]:
    """Every case for an IMU set (tampering an axis: the joined IMU set id is recomputed too)."""
    axes = tuple(encode_set(c)[0] for c in imu.axes)
    payload = encode_coupling(imu)
    valid = imu_signature(LAB_SEED, imu, VERSION)
    x, y, z = axes
    tampered = flip_one_bit(x)
    joined = canonical_bytes({**json.loads(payload.content),
                              "axes": {a: json.loads(b)
                                       for a, b in zip("xyz", (tampered, y, z), strict=True)}})

    def case(name: str, signature: bytes, refusal: str | None, axes3: tuple[bytes, ...] = axes,
             set_id: int = payload.imu_set_id) -> ImuCase:
        return ImuCase(name, axes3, payload.content, payload.crc, set_id, signature, refusal)  # type: ignore[arg-type]

    return [
        case("unsigned", b"", "not signed"),
        case("untrusted key", imu_signature(STRANGER_SEED, imu, VERSION), "not by the device's trust key"),
        case("tampered axis, ids recomputed", valid, "does not match the content", (tampered, y, z),
             crc(joined)),
        case("another sensor", imu_signature(LAB_SEED, imu, VERSION, "4712"), "does not match the content"),
        case("rolled back", imu_signature(LAB_SEED, imu, OLD_VERSION), "a rollback"),
        case("truncated signature", valid[:79], "79 bytes, not 80"),
        case("garbage signature", bytes(80), "not by the device's trust key"),
        case("valid", valid, None),
    ]


# ---------------------------------------------------------------------------------------------
# The emulated IMU's verdict on a case (BankStore: what `canical emulate` runs)
# ---------------------------------------------------------------------------------------------

#: The words of the emulated IMU's refusal for each of the C library's result codes.
REFUSAL_OF_CODE = {
    "CE_ERR_CRC": "CRC mismatch",
    "CE_ERR_UNSIGNED": "not signed",
    "CE_ERR_SIGNATURE_FORMAT": "bytes, not 80",
    "CE_ERR_KEY": "not by the device's trust key",
    "CE_ERR_SIGNATURE": "does not match the content",
    "CE_ERR_ROLLBACK": "a rollback",
}


def _store() -> Any:
    from canical.device.coefficient_banks import BankStore
    from canical.frames.imu_dictionary import AXES
    from canical.sets.admission import DeviceLimits
    from support.imu_fixtures import SERIAL

    store = BankStore(DeviceLimits(SERIAL, dict.fromkeys(AXES, 50.0)), 16384)
    store.write_trust_key(LAB_PUBLIC)
    store.trust = replace(store.trust, counter=COUNTER)
    return store


def device_verdict(case: BankCase, axis: str = "z") -> str | None:
    """The emulated IMU's refusal of an axis case (None: activated)."""
    from canical.device.coefficient_banks import BankRefusal
    from canical.frames.imu_dictionary import pack_active

    store = _store()
    store.write_content(axis, "A", case.content)
    store.write_crc(axis, "A", case.crc)
    if case.signature:
        store.write_signature(axis, "A", case.signature)
    try:
        store.activate(pack_active({axis: "A"}))
    except BankRefusal as exc:
        return exc.reason
    return None


def device_verdict3(case: ImuCase) -> str | None:
    """The emulated IMU's refusal of an IMU set case (None: activated)."""
    from canical.device.coefficient_banks import BankRefusal
    from canical.frames.imu_dictionary import AXES, pack_active

    store = _store()
    for axis, content in zip(AXES, case.axes, strict=True):
        store.write_content(axis, "A", content)
        store.write_crc(axis, "A", crc(content))
    store.write_coupling_content("A", case.coupling)
    store.write_coupling_crc("A", case.coupling_crc)
    store.write_imu_set_id("A", case.imu_set_id)
    if case.signature:
        store.write_coupling_signature("A", case.signature)
    try:
        store.activate(pack_active(dict.fromkeys(AXES, "A"), "A"))
    except BankRefusal as exc:
        return exc.reason
    return None
