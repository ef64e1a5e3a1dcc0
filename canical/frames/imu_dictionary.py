"""The IMU's CANopen object dictionary, as the EDS file declares it.

The EDS (``services/canical-imu.eds``, shipped as package data) is the one
place that fixes indexes and types: this module loads it and finds every
manufacturer-specific object by its ParameterName, so the emulated device, the
download tool and the daemon cannot disagree on an offset. What an EDS cannot
say (store/restore signatures, the bit layout of the active-bank selector, the
abort codes the device answers with, how a serial number names a sensor) is
defined here, once, for both sides.
"""

from __future__ import annotations

import functools
from dataclasses import dataclass
from importlib import resources
from pathlib import Path
from typing import TYPE_CHECKING

from canical.errors import CanicalError

if TYPE_CHECKING:
    import canopen

EDS_NAME = "canical-imu.eds"
AXES = ("x", "y", "z")
BANKS = ("A", "B")
BANK_NONE = 0  # selector value: no set active for the axis
BITS_PER_AXIS = 2
#: The coupling's two bits in the selector, above the three axes' (bits 6-7): 0 none
#: (identity), 1 coupling bank A, 2 coupling bank B.
COUPLING_SHIFT = BITS_PER_AXIS * len(AXES)

#: CiA 301 signatures: "save" / "load" as little-endian UNSIGNED32.
STORE_SIGNATURE = int.from_bytes(b"save", "little")
RESTORE_SIGNATURE = int.from_bytes(b"load", "little")
#: Written to "Provisioning" (0x2233): closes the provisioning state for good ("lock").
PROVISION_CLOSE_SIGNATURE = int.from_bytes(b"lock", "little")
PROVISIONING_OPEN = 1
PROVISIONING_CLOSED = 0

#: A bank's "Signature" sub-index: version (UNSIGNED64, little-endian), the signing key's id
#: (the first 8 bytes of the public key's SHA-256) and the Ed25519 signature (64 bytes).
SIGNATURE_VERSION_BYTES = 8
SIGNATURE_KEY_ID_BYTES = 8
SIGNATURE_ED25519_BYTES = 64
BANK_SIGNATURE_BYTES = SIGNATURE_VERSION_BYTES + SIGNATURE_KEY_ID_BYTES + SIGNATURE_ED25519_BYTES
TRUST_KEY_BYTES = 32  # an Ed25519 public key

# Bank status (sub-index "Status" of each bank record).
STATUS_EMPTY = 0
STATUS_VALID = 1
STATUS_CRC_MISMATCH = 2
STATUS_REFUSED = 3
STATUS_TEXT = {
    STATUS_EMPTY: "empty",
    STATUS_VALID: "valid",
    STATUS_CRC_MISMATCH: "CRC mismatch",
    STATUS_REFUSED: "content refused",
}

# SDO abort codes the device answers its refusals with (CiA 301 meanings).
ABORT_REFUSED = 0x08000020  # data cannot be stored: the bank's content or CRC does not check out
ABORT_DEVICE_STATE = 0x08000022  # not now: the bank is active, or another download holds the lock
ABORT_TOO_LONG = 0x06070012  # content longer than the bank's capacity
ABORT_VALUE_RANGE = 0x06090030  # selector or signature value not allowed


def sensor_id_for_serial(serial: int) -> str:
    """The ``sensor.id`` a coefficient set must carry for the device with this serial number.

    The rule is the serial number (0x1018 sub 4) as plain decimal text, so the
    id printed on the sensor's label, read over SDO and written in the YAML agree.
    """
    return str(int(serial))


def eds_path() -> Path:
    """The EDS file shipped inside the package (``services/`` links to it for deployment)."""
    return Path(str(resources.files("canical") / "data" / EDS_NAME))


def object_dictionary(node_id: int) -> canopen.ObjectDictionary:
    """A fresh object dictionary for one node (COB-IDs resolved for ``node_id``)."""
    path = eds_path()
    if not path.is_file():
        raise CanicalError(f"{path}: IMU EDS file missing from the installation")
    import canopen  # here, not at the top: `canical emulate --help` lists AXES

    return canopen.import_od(str(path), node_id)


def member(
    od: canopen.ObjectDictionary, key: int | str, sub: int | str
) -> canopen.objectdictionary.ODVariable:
    """Entry ``sub`` of record or array ``key``; the shipped EDS defines every key used here so."""
    from canopen.objectdictionary import ODVariable

    obj = od[key]
    if isinstance(obj, ODVariable):
        raise CanicalError(f"{eds_path()}: object {key!r} is a variable, not a record or array")
    return obj[sub]


def default_value(entry: canopen.objectdictionary.ODVariable) -> float:
    """An entry's default value, which every entry read for one has in the shipped EDS."""
    if entry.default is None:
        raise CanicalError(f"{eds_path()}: object {entry.name!r} has no default value")
    return entry.default


@dataclass(frozen=True)
class BankRef:
    """Where one bank lives: its record index and the sub-indexes of its entries."""

    axis: str
    bank: str
    index: int
    content: int
    crc: int
    status: int
    size: int
    signature: int


@dataclass(frozen=True)
class CouplingBankRef:
    """Where one coupling bank lives: an axis bank's entries plus the IMU set id it belongs to."""

    bank: str
    index: int
    content: int
    crc: int
    status: int
    size: int
    imu_set_id: int
    signature: int


@dataclass(frozen=True)
class ImuObjects:
    """The (index, sub-index) of every object the tools use, resolved from the EDS by name."""

    serial: tuple[int, int]
    store: tuple[int, int]
    restore: tuple[int, int]
    capacity: tuple[int, int]
    rated_range: dict[str, tuple[int, int]]
    banks: dict[tuple[str, str], BankRef]
    coupling_banks: dict[str, CouplingBankRef]
    active_banks: tuple[int, int]
    active_imu_set_id: tuple[int, int]
    active_set_id: dict[str, tuple[int, int]]
    activation_count: tuple[int, int]
    last_refusal: tuple[int, int]
    download_lock: tuple[int, int]
    correction_mode: tuple[int, int]
    stored_state: tuple[int, int]
    trust_key: tuple[int, int]
    provisioning: tuple[int, int]
    rollback_counter: tuple[int, int]
    tpdo_cob_ids: tuple[int, ...]

    def bank(self, axis: str, bank: str) -> BankRef:
        return self.banks[(axis, bank)]

    def coupling_bank(self, bank: str) -> CouplingBankRef:
        return self.coupling_banks[bank]


def _var(od: canopen.ObjectDictionary, name: str, entry: str | None = None) -> tuple[int, int]:
    obj = _variable(od, name) if entry is None else member(od, name, entry)
    return obj.index, obj.subindex


def _variable(od: canopen.ObjectDictionary, name: str) -> canopen.objectdictionary.ODVariable:
    """Plain variable ``name``; the shipped EDS defines every name used here so."""
    from canopen.objectdictionary import ODVariable

    obj = od[name]
    if not isinstance(obj, ODVariable):
        raise CanicalError(f"{eds_path()}: object {name!r} is a record or array, not a variable")
    return obj


@functools.cache
def imu_objects() -> ImuObjects:
    """Resolve the object addresses once (they do not depend on the node id)."""
    od = object_dictionary(1)
    banks = {}
    for axis in AXES:
        for bank in BANKS:
            record = f"Coefficient bank {axis.upper()} {bank}"
            banks[(axis, bank)] = BankRef(
                axis,
                bank,
                od[record].index,
                member(od, record, "Content").subindex,
                member(od, record, "CRC32").subindex,
                member(od, record, "Status").subindex,
                member(od, record, "Size").subindex,
                member(od, record, "Signature").subindex,
            )
    coupling = {}
    for bank in BANKS:
        record = f"Coupling bank {bank}"
        coupling[bank] = CouplingBankRef(
            bank,
            od[record].index,
            *(member(od, record, entry).subindex
              for entry in ("Content", "CRC32", "Status", "Size", "IMU set id", "Signature")),
        )
    return ImuObjects(
        serial=_var(od, "Identity object", "Serial number"),
        store=_var(od, "Store parameters", "Save all parameters"),
        restore=_var(od, "Restore default parameters", "Restore all default parameters"),
        capacity=_var(od, "Coefficient bank capacity"),
        rated_range={a: _var(od, "Rated range", f"Rated range {a.upper()}") for a in AXES},
        banks=banks,
        coupling_banks=coupling,
        active_banks=_var(od, "Active banks"),
        active_imu_set_id=_var(od, "Active IMU set id"),
        active_set_id={a: _var(od, "Active set id", f"Active set id {a.upper()}") for a in AXES},
        activation_count=_var(od, "Activation count"),
        last_refusal=_var(od, "Last refusal"),
        download_lock=_var(od, "Download lock"),
        correction_mode=_var(od, "Correction mode"),
        stored_state=_var(od, "Stored state"),
        trust_key=_var(od, "Trust key"),
        provisioning=_var(od, "Provisioning"),
        rollback_counter=_var(od, "Rollback counter"),
        # COB-ID base, node id 1
        tpdo_cob_ids=tuple(int(default_value(member(od, 0x1800 + i, 1))) - 1 for i in range(3)),
    )


def pack_active(selection: dict[str, str | None], coupling: str | None = None) -> int:
    """Active-bank selector value: ``{"x": "A", "y": None, ...}`` and the coupling bank → one UNSIGNED8."""
    value = 0
    for i, axis in enumerate(AXES):
        value |= _code(selection.get(axis)) << (BITS_PER_AXIS * i)
    return value | _code(coupling) << COUPLING_SHIFT


def _code(bank: str | None) -> int:
    return BANK_NONE if bank is None else BANKS.index(bank) + 1


def _bank(value: int, shift: int, what: str) -> str | None:
    code = (value >> shift) & ((1 << BITS_PER_AXIS) - 1)
    if code > len(BANKS):
        raise ValueError(f"active-bank value 0x{value:02x}: {what} code {code} names no bank")
    return None if code == BANK_NONE else BANKS[code - 1]


def unpack_active(value: int) -> dict[str, str | None]:
    """The axes' banks of a selector value (:func:`unpack_coupling` gives its coupling bank);
    raises ValueError on a code that names no bank, the coupling's included."""
    if value >> (COUPLING_SHIFT + BITS_PER_AXIS):
        raise ValueError(f"active-bank value 0x{value:02x} has bits beyond the three axes and the coupling")
    unpack_coupling(value)
    return {axis: _bank(value, BITS_PER_AXIS * i, f"axis {axis}") for i, axis in enumerate(AXES)}


def unpack_coupling(value: int) -> str | None:
    """The coupling bank a selector value names (None: no coupling, the identity)."""
    return _bank(value, COUPLING_SHIFT, "coupling")


def other_bank(bank: str | None) -> str:
    """The bank a download may write: never the active one (A when none is active)."""
    return "A" if bank in (None, "B") else "B"
