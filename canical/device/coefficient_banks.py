"""The IMU's coefficient banks: what the device stores, and the rules it enforces.

Two banks (A, B) per axis, each holding a set's canonical bytes and a declared
CRC32, and one selector naming the active bank of every axis. The rules:

* a write to a bank that is active is refused, so the running set can never be
  half-overwritten: a download always goes to the other bank;
* activation is a single write of the whole selector. Every bank it newly
  selects is checked first (content present, CRC32 over the bytes equal to the
  declared one, every field valid, set admitted for this device: serial, axis,
  span — :mod:`canical.sets.admission`); only if all pass does the selector
  change, all axes at once. Switching a calibrated axis to "none" is refused;
* the selector and banks survive a power cycle only once stored (CiA 301 "save"
  to 0x1010). The state file is replaced atomically, so a device that dies
  mid-store boots with the old state or the new one, never a mix; at boot
  every active bank is checked again and an axis whose bank fails is dropped
  to "none" (logged), never run on a damaged set;
* an IMU set's coupling has two banks of its own (:func:`~canical.device.bank_payload.encode_coupling`:
  the IMU set without its axes, and the IMU set's id), selected by the selector's bits 6-7 in
  the same single write. Activating one checks it alone (CRC, fields, the matrix by
  :func:`canical.sets.imu_set.check_coupling`, sensor) and that it belongs to the three axes
  selected with it (they and it make the IMU set its id names); no coupling is the identity,
  so a device without one corrects as a single-axis device always has. An active coupling,
  like a calibrated axis, cannot be switched to none, and axes it does not belong to cannot
  be activated under it: a new IMU set replaces it whole;
* signed sets (:mod:`canical.device.bank_signature`): a bank's "Signature" (cleared by a write of
  its content) holds the lab's signature of it. Once a trust key is provisioned, activation needs,
  for every bank it newly selects, a valid signature by that key for this device's sensor id, of
  a version not below the anti-rollback counter (the highest version ever activated); an IMU
  set's axes are covered by its coupling bank's signature, over the whole IMU set. The key is
  writable only while provisioning is open; closing it is one-way. Key, provisioning state and
  counter are written to the state file as soon as they change (beside the banks as last stored),
  so a power cycle keeps them; a state file without them loads as a device never provisioned.
  Without a key the device activates as it always has;
* an optional cooperative lock (a token) stops a second honest download tool
  from interleaving with a running one; it expires after :data:`LOCK_LEASE_S`
  without activity, so a tool that died does not lock the device forever.

This module has no bus in it: :mod:`canical.device.emulated_imu` maps SDO accesses to
these methods and turns :class:`BankRefusal` into an SDO abort code.
"""

from __future__ import annotations

import base64
import json
import logging
import os
import threading
import time
import zlib
from collections.abc import Callable
from dataclasses import dataclass, field, replace
from pathlib import Path
from typing import Generic, TypeVar

from canical.device.bank_payload import CouplingContent, decode_coupling, decode_set, join_imu_set
from canical.device.bank_signature import joined_imu_canonical, verify_bank
from canical.errors import CanicalError
from canical.files.atomic_file import write_text_atomic
from canical.frames.imu_dictionary import (
    ABORT_DEVICE_STATE,
    ABORT_REFUSED,
    ABORT_TOO_LONG,
    ABORT_VALUE_RANGE,
    AXES,
    BANK_SIGNATURE_BYTES,
    BANKS,
    PROVISION_CLOSE_SIGNATURE,
    STATUS_CRC_MISMATCH,
    STATUS_EMPTY,
    STATUS_REFUSED,
    STATUS_VALID,
    TRUST_KEY_BYTES,
    pack_active,
    sensor_id_for_serial,
    unpack_active,
    unpack_coupling,
)
from canical.sets.admission import DeviceLimits, admission_problem
from canical.sets.coefficients import CoefficientSet
from canical.sets.imu_set import ImuSet
from canical.sets.signing import key_id_of

STATE_FORMAT = "canical-imu-banks 1"
LOCK_LEASE_S = 5.0

log = logging.getLogger("canical.imu")


class BankRefusal(Exception):
    """A write the device refuses: an SDO abort code and a one-line reason."""

    def __init__(self, code: int, reason: str) -> None:
        super().__init__(reason)
        self.code = code
        self.reason = reason


@dataclass
class Bank:
    content: bytes = b""
    crc: int = 0
    imu_set_id: int = 0  # coupling banks only: the IMU set the content belongs to
    signature: bytes = b""  # the "Signature" sub-index: empty (unsigned) until written


@dataclass(frozen=True)
class Trust:
    """What the device trusts: the provisioned key (empty: none), whether provisioning is still
    open, and the anti-rollback counter (the highest signed version ever activated)."""

    key: bytes = b""
    provisioning_open: bool = True
    counter: int = 0

    def to_dict(self) -> dict[str, object]:
        return {"key": base64.b64encode(self.key).decode(), "provisioning_open": self.provisioning_open,
                "counter": self.counter}


#: The trust of a device whose stored trust could not be read: no key and provisioning closed (a
#: state no provisioning reaches, since closing needs a key): every activation is refused until the
#: device is provisioned again at the factory (its state removed), never reopened by the damage.
DAMAGED_TRUST = Trust(b"", provisioning_open=False, counter=0)


def trust_from_dict(entry: dict[str, object]) -> Trust:
    """A state file's trust section; any defect is a ValueError (the state is then unreadable)."""
    key = base64.b64decode(str(entry["key"]), validate=True)
    opened, counter = entry["provisioning_open"], entry["counter"]
    if len(key) not in (0, TRUST_KEY_BYTES) or not isinstance(opened, bool) or not isinstance(counter, int):
        raise ValueError("trust section malformed")
    return Trust(key, opened, counter)


@dataclass(frozen=True)
class CouplingCheck:
    """A coupling bank checked on its own: status, its parsed content when valid, the reason when not."""

    status: int
    envelope: CouplingContent | None = None
    reason: str = ""


@dataclass(frozen=True)
class BankCheck:
    """Result of validating one bank: status code, the set when valid, the reason when not."""

    status: int
    cset: CoefficientSet | None = None
    reason: str = ""


CheckT = TypeVar("CheckT", "BankCheck", "CouplingCheck")


@dataclass(frozen=True)
class CachedCheck(Generic[CheckT]):
    """A bank's check and the content and CRC it was made for: valid while the bank holds them."""

    content: bytes
    crc: int
    result: CheckT

    def holds(self, bank: Bank) -> bool:
        """Whether the bank still holds what was checked (the same bytes object, the same CRC)."""
        return self.content is bank.content and self.crc == bank.crc


@dataclass(frozen=True)
class JoinedImu:
    """The IMU set the active banks make, and what it was joined from (banks, contents, ids)."""

    key: tuple[object, ...]
    imu: ImuSet | None


@dataclass
class BankStore:
    """Banks, selector and lock of one device; thread-safe (SDO and streaming threads share it)."""

    limits: DeviceLimits
    capacity: int
    state_path: Path | None = None
    clock: Callable[[], float] = time.monotonic
    banks: dict[tuple[str, str], Bank] = field(default_factory=dict)
    active: dict[str, str | None] = field(default_factory=lambda: dict.fromkeys(AXES))
    stored_active: dict[str, str | None] = field(default_factory=lambda: dict.fromkeys(AXES))
    coupling: dict[str, Bank] = field(default_factory=lambda: {b: Bank() for b in BANKS})
    active_coupling: str | None = None
    stored_coupling: str | None = None
    activation_count: int = 0
    last_refusal: str = "none"
    lock_token: int = 0
    lock_seen: float = 0.0
    generation: int = 0  # bumped on every activation, for listeners
    trust: Trust = field(default_factory=Trust)

    def __post_init__(self) -> None:
        self._lock = threading.RLock()
        self._checks: dict[tuple[str, str], CachedCheck[BankCheck]] = {}
        self._coupling_checks: dict[str, CachedCheck[CouplingCheck]] = {}
        self._active_imu = JoinedImu((), None)
        self._stored_body = self._body(dict.fromkeys(AXES), None)  # what the state file's banks say
        for key in ((a, b) for a in AXES for b in BANKS):
            self.banks.setdefault(key, Bank())

    # ---------------------------------------------------------------------------------------
    # Reads
    # ---------------------------------------------------------------------------------------

    def check(self, axis: str, bank: str) -> BankCheck:
        """Validate a bank (cached per content and CRC): the device's whole acceptance test."""
        with self._lock:
            b = self.banks[(axis, bank)]
            cached = self._checks.get((axis, bank))
            if cached is not None and cached.holds(b):
                return cached.result
            result = self._check(axis, bank, b)
            self._checks[(axis, bank)] = CachedCheck(b.content, b.crc, result)
            return result

    def _check(self, axis: str, bank: str, b: Bank) -> BankCheck:
        where = f"bank {axis.upper()} {bank}"
        if not b.content:
            return BankCheck(STATUS_EMPTY, reason=f"{where} is empty")
        actual = zlib.crc32(b.content) & 0xFFFFFFFF
        if actual != b.crc:
            return BankCheck(
                STATUS_CRC_MISMATCH,
                reason=f"{where}: CRC mismatch (declared 0x{b.crc:08x}, content gives 0x{actual:08x})",
            )
        try:
            cset = decode_set(b.content, b.crc, where)
        except CanicalError as exc:
            return BankCheck(STATUS_REFUSED, reason=str(exc))
        problem = admission_problem(cset, axis, self.limits)
        if problem:
            return BankCheck(STATUS_REFUSED, reason=f"{where}: {problem}")
        return BankCheck(STATUS_VALID, cset)

    def check_coupling(self, bank: str) -> CouplingCheck:
        """A coupling bank on its own (cached per content and CRC); membership is checked at activation."""
        with self._lock:
            b = self.coupling[bank]
            cached = self._coupling_checks.get(bank)
            if cached is not None and cached.holds(b):
                return cached.result
            result = self._check_coupling(bank, b)
            self._coupling_checks[bank] = CachedCheck(b.content, b.crc, result)
            return result

    def _check_coupling(self, bank: str, b: Bank) -> CouplingCheck:
        where = f"coupling bank {bank}"
        if not b.content:
            return CouplingCheck(STATUS_EMPTY, reason=f"{where} is empty")
        actual = zlib.crc32(b.content) & 0xFFFFFFFF
        if actual != b.crc:
            return CouplingCheck(
                STATUS_CRC_MISMATCH,
                reason=f"{where}: CRC mismatch (declared 0x{b.crc:08x}, content gives 0x{actual:08x})",
            )
        try:
            envelope = decode_coupling(b.content, b.crc, where)
        except CanicalError as exc:
            return CouplingCheck(STATUS_REFUSED, reason=str(exc))
        serial = sensor_id_for_serial(self.limits.serial)
        if envelope.sensor_id != serial:
            return CouplingCheck(STATUS_REFUSED, reason=f"{where}: IMU set for sensor "
                                 f"{envelope.sensor_id!r}, this device is serial {serial}")
        return CouplingCheck(STATUS_VALID, envelope)

    def _joined(self, bank: str, axes: dict[str, str | None]) -> ImuSet:
        """The IMU set coupling bank ``bank`` makes with the axis banks ``axes``, or the reason
        why not (CanicalError): the coupling is valid, every axis selected and valid, and
        together they make the IMU set the coupling bank's id names."""
        result = self.check_coupling(bank)
        if result.envelope is None:
            raise CanicalError(result.reason)
        missing = [a for a in AXES if axes[a] is None]
        if missing:
            raise CanicalError(f"coupling bank {bank} needs all three axes; no set for {', '.join(missing)}")
        sets = []
        for axis in AXES:
            checked = self.check(axis, axes[axis])  # type: ignore[arg-type]
            if checked.cset is None:
                raise CanicalError(checked.reason)
            sets.append(checked.cset)
        return join_imu_set(result.envelope, tuple(sets), self.coupling[bank].imu_set_id,
                            f"coupling bank {bank}")

    def active_imu_set(self) -> ImuSet | None:
        """The IMU set the device runs (its coupling applied), or None: no coupling, identity."""
        with self._lock:
            if self.active_coupling is None:
                return None
            key = (self.active_coupling, self.coupling[self.active_coupling].content,
                   *(self.active[a] for a in AXES), *(self.active_id(a) for a in AXES))
            if self._active_imu.key != key:
                self._active_imu = JoinedImu(key, self._joined(self.active_coupling, self.active))
            return self._active_imu.imu

    def active_imu_set_id(self) -> int:
        with self._lock:
            bank = self.active_coupling
            return 0 if bank is None else self.coupling[bank].imu_set_id

    def active_sets(self) -> dict[str, CoefficientSet]:
        """The sets the device runs now, by axis (valid by construction)."""
        with self._lock:
            out = {}
            for axis, bank in self.active.items():
                if bank is not None:
                    cset = self.check(axis, bank).cset
                    if cset is not None:
                        out[axis] = cset
            return out

    def active_id(self, axis: str) -> int:
        with self._lock:
            bank = self.active[axis]
            return 0 if bank is None else self.banks[(axis, bank)].crc

    def active_value(self) -> int:
        with self._lock:
            return pack_active(self.active, self.active_coupling)

    def stored_value(self) -> int:
        with self._lock:
            return pack_active(self.stored_active, self.stored_coupling)

    def current_lock(self) -> int:
        with self._lock:
            if self.lock_token and self.clock() - self.lock_seen > LOCK_LEASE_S:
                self.lock_token = 0
            return self.lock_token

    # ---------------------------------------------------------------------------------------
    # Writes (each raises BankRefusal when the device says no)
    # ---------------------------------------------------------------------------------------

    def _refuse(self, code: int, reason: str) -> BankRefusal:
        self.last_refusal = reason
        log.warning("refused: %s", reason)
        return BankRefusal(code, reason)

    def _touch(self) -> None:
        if self.lock_token:
            self.lock_seen = self.clock()

    def _writable(self, axis: str, bank: str) -> Bank:
        if self.active[axis] == bank:
            raise self._refuse(
                ABORT_DEVICE_STATE, f"bank {axis.upper()} {bank} is active: write the other bank"
            )
        return self.banks[(axis, bank)]

    def write_content(self, axis: str, bank: str, data: bytes) -> None:
        with self._lock:
            b = self._writable(axis, bank)
            if len(data) > self.capacity:
                raise self._refuse(
                    ABORT_TOO_LONG, f"bank {axis.upper()} {bank}: {len(data)} bytes, capacity {self.capacity}"
                )
            b.content = bytes(data)
            b.signature = b""
            self._touch()

    def write_signature(self, axis: str, bank: str, data: bytes) -> None:
        """A bank's signature (checked at activation, like its content)."""
        with self._lock:
            self._writable(axis, bank).signature = self._signature_bytes(data, f"bank {axis.upper()} {bank}")
            self._touch()

    def _signature_bytes(self, data: bytes, where: str) -> bytes:
        if len(data) > BANK_SIGNATURE_BYTES:
            raise self._refuse(ABORT_TOO_LONG, f"{where}: signature of {len(data)} bytes, at most "
                                               f"{BANK_SIGNATURE_BYTES}")
        return bytes(data)

    def write_crc(self, axis: str, bank: str, crc: int) -> None:
        with self._lock:
            self._writable(axis, bank).crc = int(crc) & 0xFFFFFFFF
            self._touch()

    def _writable_coupling(self, bank: str) -> Bank:
        if self.active_coupling == bank:
            raise self._refuse(ABORT_DEVICE_STATE, f"coupling bank {bank} is active: write the other bank")
        return self.coupling[bank]

    def write_coupling_content(self, bank: str, data: bytes) -> None:
        with self._lock:
            b = self._writable_coupling(bank)
            if len(data) > self.capacity:
                raise self._refuse(
                    ABORT_TOO_LONG, f"coupling bank {bank}: {len(data)} bytes, capacity {self.capacity}"
                )
            b.content = bytes(data)
            b.signature = b""
            self._touch()

    def write_coupling_signature(self, bank: str, data: bytes) -> None:
        """A coupling bank's signature: the IMU set's (checked at activation with its axes)."""
        with self._lock:
            self._writable_coupling(bank).signature = self._signature_bytes(data, f"coupling bank {bank}")
            self._touch()

    def write_coupling_crc(self, bank: str, crc: int) -> None:
        with self._lock:
            self._writable_coupling(bank).crc = int(crc) & 0xFFFFFFFF
            self._touch()

    def write_imu_set_id(self, bank: str, imu_set_id: int) -> None:
        with self._lock:
            self._writable_coupling(bank).imu_set_id = int(imu_set_id) & 0xFFFFFFFF
            self._touch()

    def write_trust_key(self, data: bytes) -> None:
        """Provision the public key banks must be signed by: only while provisioning is open."""
        with self._lock:
            if not self.trust.provisioning_open:
                raise self._refuse(ABORT_DEVICE_STATE,
                                   "provisioning is closed: the trust key cannot be changed")
            if len(data) != TRUST_KEY_BYTES:
                raise self._refuse(ABORT_VALUE_RANGE,
                                   f"trust key of {len(data)} bytes, not {TRUST_KEY_BYTES}: an Ed25519 key")
            self.trust = replace(self.trust, key=bytes(data))
            self._persist()
            log.info("trust key provisioned (key id %s)", key_id_of(self.trust.key))

    def close_provisioning(self, value: int) -> None:
        """Close provisioning for good (the value must be the signature "lock"), once a key is in."""
        with self._lock:
            if value != PROVISION_CLOSE_SIGNATURE:
                raise self._refuse(ABORT_VALUE_RANGE, "provisioning closes by writing the signature 'lock'")
            if not self.trust.key:
                raise self._refuse(ABORT_DEVICE_STATE, "no trust key provisioned: closing would leave the "
                                                       "device unable to check signatures for good")
            self.trust = replace(self.trust, provisioning_open=False)
            self._persist()
            log.info("provisioning closed: trust key %s for good", key_id_of(self.trust.key))

    def take_lock(self, token: int) -> None:
        """Nonzero token: take (or renew) the lock; 0: release it."""
        with self._lock:
            held = self.current_lock()
            if token and held and held != token:
                raise self._refuse(
                    ABORT_DEVICE_STATE, f"another download holds the lock (token 0x{held:08x})"
                )
            self.lock_token = int(token)
            self.lock_seen = self.clock()

    def activate(self, value: int) -> None:
        """One write of the whole selector: validate every newly selected bank (and a selected
        coupling against the axes selected with it), then switch all."""
        with self._lock:
            try:
                wanted = unpack_active(value)
                coupling = unpack_coupling(value)
            except ValueError as exc:
                raise self._refuse(ABORT_VALUE_RANGE, str(exc)) from None
            changes = {a: b for a, b in wanted.items() if b != self.active[a]}
            for axis, bank in changes.items():
                if bank is None:
                    raise self._refuse(
                        ABORT_VALUE_RANGE,
                        f"axis {axis} is calibrated: it cannot be switched to no set (restore defaults)",
                    )
                result = self.check(axis, bank)
                if result.status != STATUS_VALID:
                    raise self._refuse(ABORT_REFUSED, f"activation refused: {result.reason}")
            coupling_changes = coupling != self.active_coupling
            if coupling_changes and coupling is None:
                raise self._refuse(
                    ABORT_VALUE_RANGE,
                    "the coupling of an IMU set is active: it cannot be switched to none (restore defaults)",
                )
            if coupling is not None and (changes or coupling_changes):
                try:
                    self._joined(coupling, {**self.active, **changes})
                except CanicalError as exc:
                    raise self._refuse(ABORT_REFUSED, f"activation refused: {exc}") from None
            self._touch()
            if not changes and not coupling_changes:
                return
            versions = self._signed_versions(changes, coupling)
            before = {a: self.active_id(a) for a in changes}
            before_imu = self.active_imu_set_id()
            self.active.update(changes)
            self.active_coupling = coupling
            self.activation_count += 1
            self.generation += 1
            if versions and max(versions) > self.trust.counter:
                self.trust = replace(self.trust, counter=max(versions))
                self._persist()
            for axis, bank in changes.items():
                log.info(
                    "activation %d: axis %s bank %s set 0x%08x (was 0x%08x), serial %d",
                    self.activation_count, axis, bank, self.active_id(axis), before[axis], self.limits.serial,
                )
            if coupling_changes or (coupling is not None and changes):
                log.info("activation %d: coupling bank %s IMU set 0x%08x (was 0x%08x)", self.activation_count,
                         coupling, self.active_imu_set_id(), before_imu)

    def _signed_versions(self, changes: dict[str, str | None], coupling: str | None) -> list[int]:
        """With a trust key: the signed version of every bank an activation newly selects (an IMU
        set's, on its coupling bank, covers its axes), else a refusal naming the first bad one.
        Without a key: none (no signature needed)."""
        if self.trust == DAMAGED_TRUST:
            raise self._refuse(ABORT_DEVICE_STATE, "activation refused: the device's stored trust is "
                                                   "damaged; it takes no set until provisioned again at the "
                                                   "factory")
        if not self.trust.key:
            return []
        sensor = sensor_id_for_serial(self.limits.serial)
        try:
            if coupling is not None:
                selected = {**self.active, **changes}
                axes = tuple(self.banks[(a, selected[a])].content for a in AXES)  # type: ignore[index]
                b = self.coupling[coupling]
                canonical = joined_imu_canonical(b.content, axes)
                return [verify_bank(b.signature, canonical, sensor, self.trust.key, self.trust.counter,
                                    f"coupling bank {coupling} (IMU set 0x{b.imu_set_id:08x})")]
            return [verify_bank(self.banks[(a, k)].signature, self.banks[(a, k)].content, sensor,
                                self.trust.key, self.trust.counter, f"bank {a.upper()} {k}")
                    for a, k in changes.items() if k is not None]
        except CanicalError as exc:
            raise self._refuse(ABORT_REFUSED, f"activation refused: {exc}") from None

    def store(self, signature_ok: bool) -> None:
        """CiA 301 store: persist banks and selector (atomically) to the state file."""
        with self._lock:
            if not signature_ok:
                raise self._refuse(ABORT_REFUSED, "store needs the signature 'save'")
            self._stored_body = self._body(self.active, self.active_coupling)
            self._persist()
            self.stored_active = dict(self.active)
            self.stored_coupling = self.active_coupling
            self._touch()
            log.info("stored: active banks %s", _describe(self.active))

    def restore_defaults(self, signature_ok: bool) -> None:
        """CiA 301 restore: the next boot starts from factory defaults (no sets); RAM is unchanged."""
        with self._lock:
            if not signature_ok:
                raise self._refuse(ABORT_REFUSED, "restore needs the signature 'load'")
            empty = BankStore(self.limits, self.capacity)
            empty.activation_count = self.activation_count
            self._stored_body = empty._body(empty.active, None)  # the trust is kept: it is not a set
            self._persist()
            self.stored_active = dict.fromkeys(AXES)
            self.stored_coupling = None
            log.info("restore defaults: no coefficient sets after the next power cycle")

    # ---------------------------------------------------------------------------------------
    # Persistence
    # ---------------------------------------------------------------------------------------

    def _body(self, active: dict[str, str | None], coupling: str | None) -> dict[str, object]:
        """The banks and selector as a store writes them (the state file's body)."""
        return {
            "format": STATE_FORMAT,
            "serial": self.limits.serial,
            "active": pack_active(active, coupling),
            "activation_count": self.activation_count,
            "banks": {
                f"{a}.{b}": {"content": base64.b64encode(bank.content).decode(), "crc": bank.crc,
                             "signature": base64.b64encode(bank.signature).decode()}
                for (a, b), bank in self.banks.items()
                if bank.content or bank.crc
            },
            "coupling": {
                b: {"content": base64.b64encode(bank.content).decode(), "crc": bank.crc,
                    "imu_set_id": bank.imu_set_id, "signature": base64.b64encode(bank.signature).decode()}
                for b, bank in self.coupling.items()
                if bank.content or bank.crc or bank.imu_set_id
            },
        }

    def _persist(self) -> None:
        """Write the state file: the banks as last stored, the trust as it is now (atomically)."""
        if self.state_path is not None:
            text = json.dumps({**self._stored_body, "trust": self.trust.to_dict()}, indent=1) + "\n"
            write_text_atomic(self.state_path, text)

    @classmethod
    def boot(
        cls, limits: DeviceLimits, capacity: int, state_path: str | os.PathLike[str] | None
    ) -> BankStore:
        """Power on: load the stored state (if any) and re-check every active bank."""
        store = cls(limits, capacity, Path(state_path) if state_path else None)
        if store.state_path is None or not store.state_path.exists():
            return store
        try:
            content = json.loads(store.state_path.read_text(encoding="utf-8"))
            if content.get("format") != STATE_FORMAT:
                raise ValueError(f"format {content.get('format')!r}")
            if content.get("serial") != limits.serial:
                raise ValueError(f"state belongs to serial {content.get('serial')}")
            for key, entry in content["banks"].items():
                axis, bank = key.split(".")
                store.banks[(axis, bank)] = Bank(base64.b64decode(entry["content"]), int(entry["crc"]),
                                                 signature=base64.b64decode(entry.get("signature", "")))
            for bank, entry in content.get("coupling", {}).items():
                if bank not in BANKS:
                    raise ValueError(f"coupling bank {bank!r}")
                store.coupling[bank] = Bank(base64.b64decode(entry["content"]), int(entry["crc"]),
                                            int(entry["imu_set_id"]),
                                            base64.b64decode(entry.get("signature", "")))
            selected = unpack_active(int(content["active"]))
            coupling = unpack_coupling(int(content["active"]))
            store.activation_count = int(content.get("activation_count", 0))
            store.trust = trust_from_dict(content["trust"]) if "trust" in content else Trust()
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            log.error("stored state %s unreadable (%s): starting without coefficient sets", state_path, exc)
            fresh = cls(limits, capacity, store.state_path)
            fresh.trust = _surviving_trust(store.state_path)
            return fresh
        for axis, bank in selected.items():
            if bank is None:
                continue
            result = store.check(axis, bank)
            if result.status == STATUS_VALID:
                store.active[axis] = bank
            else:
                log.error("boot: axis %s left without a set: %s", axis, result.reason)
        if coupling is not None:
            try:
                store._joined(coupling, store.active)
                store.active_coupling = coupling
            except CanicalError as exc:
                log.error("boot: coupling left out (identity): %s", exc)
        store.stored_active = dict(store.active)
        store.stored_coupling = store.active_coupling
        store._stored_body = {k: v for k, v in content.items() if k != "trust"}
        log.info("boot: active banks %s", _describe(store.active, store))
        if store.active_coupling is not None:
            log.info("boot: coupling bank %s, IMU set 0x%08x", store.active_coupling,
                     store.active_imu_set_id())
        if store.trust.key:
            log.info("boot: trust key %s, provisioning %s, rollback counter %d", key_id_of(store.trust.key),
                     "open" if store.trust.provisioning_open else "closed", store.trust.counter)
        return store


def _surviving_trust(path: Path) -> Trust:
    """The trust section of a state file whose banks cannot be read: a damaged bank must not
    reopen provisioning or reset the counter. A file from before trust existed (readable, with
    no trust section) is a device never provisioned; a trust section that cannot be read, or a
    file that cannot be read at all, fails closed (:data:`DAMAGED_TRUST`): reopening provisioning
    would let anyone who can damage the file install their own key."""
    try:
        content = json.loads(path.read_text(encoding="utf-8"))
    except (OSError, ValueError) as exc:
        log.error("stored state %s unreadable (%s): trust damaged, no set is activated", path, exc)
        return DAMAGED_TRUST
    if not isinstance(content, dict) or "trust" not in content:
        return Trust()
    try:
        return trust_from_dict(content["trust"])
    except (ValueError, KeyError, TypeError, AttributeError) as exc:
        log.error("stored state %s: trust unreadable (%s): no set is activated", path, exc)
        return DAMAGED_TRUST


def _describe(active: dict[str, str | None], store: BankStore | None = None) -> str:
    parts = []
    for axis in AXES:
        bank = active.get(axis)
        if bank is None:
            parts.append(f"{axis}=none")
        elif store is not None:
            parts.append(f"{axis}={bank}(0x{store.banks[(axis, bank)].crc:08x})")
        else:
            parts.append(f"{axis}={bank}")
    return " ".join(parts)
