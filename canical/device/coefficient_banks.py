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
from dataclasses import dataclass, field
from pathlib import Path

from canical.atomic_file import write_text_atomic
from canical.device.bank_payload import decode_set
from canical.errors import CanicalError
from canical.imu_dictionary import (
    ABORT_DEVICE_STATE,
    ABORT_REFUSED,
    ABORT_TOO_LONG,
    ABORT_VALUE_RANGE,
    AXES,
    BANKS,
    STATUS_CRC_MISMATCH,
    STATUS_EMPTY,
    STATUS_REFUSED,
    STATUS_VALID,
    pack_active,
    unpack_active,
)
from canical.sets.admission import DeviceLimits, admission_problem
from canical.sets.coefficients import CoefficientSet

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


@dataclass(frozen=True)
class BankCheck:
    """Result of validating one bank: status code, the set when valid, the reason when not."""

    status: int
    cset: CoefficientSet | None = None
    reason: str = ""


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
    activation_count: int = 0
    last_refusal: str = "none"
    lock_token: int = 0
    lock_seen: float = 0.0
    generation: int = 0  # bumped on every activation, for listeners

    def __post_init__(self) -> None:
        self._lock = threading.RLock()
        self._checks: dict[tuple[str, str], tuple[bytes, int, BankCheck]] = {}
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
            if cached and cached[0] is b.content and cached[1] == b.crc:
                return cached[2]
            result = self._check(axis, bank, b)
            self._checks[(axis, bank)] = (b.content, b.crc, result)
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
            return pack_active(self.active)

    def stored_value(self) -> int:
        with self._lock:
            return pack_active(self.stored_active)

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
            self._touch()

    def write_crc(self, axis: str, bank: str, crc: int) -> None:
        with self._lock:
            self._writable(axis, bank).crc = int(crc) & 0xFFFFFFFF
            self._touch()

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
        """One write of the whole selector: validate every newly selected bank, then switch all."""
        with self._lock:
            try:
                wanted = unpack_active(value)
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
            self._touch()
            if not changes:
                return
            before = {a: self.active_id(a) for a in changes}
            self.active.update(changes)
            self.activation_count += 1
            self.generation += 1
            for axis, bank in changes.items():
                log.info(
                    "activation %d: axis %s bank %s set 0x%08x (was 0x%08x), serial %d",
                    self.activation_count, axis, bank, self.active_id(axis), before[axis], self.limits.serial,
                )

    def store(self, signature_ok: bool) -> None:
        """CiA 301 store: persist banks and selector (atomically) to the state file."""
        with self._lock:
            if not signature_ok:
                raise self._refuse(ABORT_REFUSED, "store needs the signature 'save'")
            if self.state_path is not None:
                write_text_atomic(self.state_path, self._state_text())
            self.stored_active = dict(self.active)
            self._touch()
            log.info("stored: active banks %s", _describe(self.active))

    def restore_defaults(self, signature_ok: bool) -> None:
        """CiA 301 restore: the next boot starts from factory defaults (no sets); RAM is unchanged."""
        with self._lock:
            if not signature_ok:
                raise self._refuse(ABORT_REFUSED, "restore needs the signature 'load'")
            if self.state_path is not None:
                empty = BankStore(self.limits, self.capacity)
                empty.activation_count = self.activation_count
                write_text_atomic(self.state_path, empty._state_text())
            self.stored_active = dict.fromkeys(AXES)
            log.info("restore defaults: no coefficient sets after the next power cycle")

    # ---------------------------------------------------------------------------------------
    # Persistence
    # ---------------------------------------------------------------------------------------

    def _state_text(self) -> str:
        return json.dumps(
            {
                "format": STATE_FORMAT,
                "serial": self.limits.serial,
                "active": pack_active(self.active),
                "activation_count": self.activation_count,
                "banks": {
                    f"{a}.{b}": {"content": base64.b64encode(bank.content).decode(), "crc": bank.crc}
                    for (a, b), bank in self.banks.items()
                    if bank.content or bank.crc
                },
            },
            indent=1,
        ) + "\n"

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
                store.banks[(axis, bank)] = Bank(base64.b64decode(entry["content"]), int(entry["crc"]))
            selected = unpack_active(int(content["active"]))
            store.activation_count = int(content.get("activation_count", 0))
        except (OSError, ValueError, KeyError, TypeError, AttributeError) as exc:
            log.error("stored state %s unreadable (%s): starting without coefficient sets", state_path, exc)
            return cls(limits, capacity, store.state_path)
        for axis, bank in selected.items():
            if bank is None:
                continue
            result = store.check(axis, bank)
            if result.status == STATUS_VALID:
                store.active[axis] = bank
            else:
                log.error("boot: axis %s left without a set: %s", axis, result.reason)
        store.stored_active = dict(store.active)
        log.info("boot: active banks %s", _describe(store.active, store))
        return store


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
