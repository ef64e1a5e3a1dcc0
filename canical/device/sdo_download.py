"""Coefficient sets to and from an IMU over CANopen SDO: push, pull, and what the device runs.

A push, for the sets given (one per axis):

1. reads the device's serial number, rated ranges and bank capacity and refuses,
   before writing anything, a set for another sensor, another axis, too narrow a
   span, terms the device's evaluator cannot hold (more spline terms than its slots)
   or content longer than its banks (:mod:`canical.sets.admission`, the checks the
   device makes);
2. takes the device's download lock (a random token; a second tool is refused);
3. writes each set's canonical bytes and CRC32 into the axis's *inactive* bank, and the
   set file's signature (:mod:`canical.device.bank_signature`) when it is signed, reads them
   back and compares, and checks the device reports the bank valid;
4. activates all axes with one write of the active-bank selector (the device
   re-validates every bank it switches to, and switches all or none);
5. stores (CiA 301 "save" to 0x1010) so the new sets survive a power cycle;
6. reads back what the device runs and stores, and checks it is what was pushed.

An IMU set pushes its three axes as above and its coupling into the inactive
coupling bank (content, CRC32, the IMU set's id and the IMU set's signature), read back and compared like
the axes, and the one selector write activates axes and coupling together (the
device checks the coupling belongs to the axes). A device running an IMU set
refuses single-axis sets under its coupling: the tool says so before writing.

Any failure stops the push with one line naming the node, the step and the
device's reason; the device keeps the set it ran before (an interrupted
download only ever touched an inactive bank). A pull uploads the active banks
and accepts them only if CRC, fields and the device's "Active set id" agree; an
IMU set pull also uploads the active coupling bank and rebuilds the IMU set,
accepted only if it is the one the device's "Active IMU set id" names.
"""

from __future__ import annotations

import contextlib
import secrets
import struct
import time
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field

import can
import canopen
from canopen.sdo import SdoAbortedError, SdoCommunicationError

from canical.device.bank_payload import (
    CouplingPayload,
    decode_coupling,
    decode_set,
    encode_coupling,
    encode_set,
    join_imu_set,
)
from canical.device.can_network import DEFAULT_SDO_TIMEOUT_S
from canical.errors import CanicalError
from canical.frames.imu_dictionary import (
    ABORT_DEVICE_STATE,
    ABORT_REFUSED,
    ABORT_TOO_LONG,
    ABORT_VALUE_RANGE,
    AXES,
    STATUS_TEXT,
    STATUS_VALID,
    STORE_SIGNATURE,
    BankRef,
    CouplingBankRef,
    imu_objects,
    object_dictionary,
    other_bank,
    pack_active,
    sensor_id_for_serial,
    unpack_active,
    unpack_coupling,
)
from canical.sets.admission import DeviceLimits, admission_problem
from canical.sets.coefficients import CoefficientSet
from canical.sets.imu_set import ImuSet

DEFAULT_TIMEOUT_S = DEFAULT_SDO_TIMEOUT_S
#: Abort codes after which the device's "Last refusal" text says why.
EXPLAINED_ABORTS = (ABORT_REFUSED, ABORT_DEVICE_STATE, ABORT_TOO_LONG, ABORT_VALUE_RANGE)


class DeviceSilent(CanicalError):
    """The device stopped answering (timeout): gone, powered off, or the bus is down."""


#: SDO aborts that say an object or sub-index is not in the node's dictionary at all.
NOT_IN_DICTIONARY = (0x06020000, 0x06090011)
IDENTITY_VENDOR, IDENTITY_PRODUCT = (0x1018, 1), (0x1018, 2)
#: SDO aborts a "Signature" read answers for a bank without one: no data (an empty DOMAIN), or
#: the sub-index not in the dictionary (firmware older than signed banks).
NO_SIGNATURE = (0x08000024, *NOT_IN_DICTIONARY)


class NotCanicalDevice(CanicalError):
    """The node answers, but has no coefficient objects: it does not run canical's firmware."""


class ImuClient:
    """SDO access to one IMU node; every failure is one :class:`CanicalError` line."""

    def __init__(self, network: canopen.Network, node_id: int, timeout_s: float = DEFAULT_TIMEOUT_S) -> None:
        self.node_id = node_id
        self.timeout_s = timeout_s
        self.objects = imu_objects()
        self.node = canopen.RemoteNode(node_id, object_dictionary(node_id))
        self.node.sdo.RESPONSE_TIMEOUT = timeout_s
        network.add_node(self.node)
        self.network = network

    def close(self) -> None:
        """Stop listening for this node's SDO responses."""
        del self.network[self.node_id]

    # ---------------------------------------------------------------------------------------
    # Raw access with error mapping
    # ---------------------------------------------------------------------------------------

    def _fail(self, exc: Exception, what: str) -> CanicalError:
        where = f"node 0x{self.node_id:02x}"
        if isinstance(exc, SdoCommunicationError):
            return DeviceSilent(f"{where}: no answer while {what} (after {self.timeout_s:g} s): "
                                f"device gone, powered off or bus down")
        if isinstance(exc, SdoAbortedError):
            text = SdoAbortedError.CODES.get(exc.code, "abort")
            reason = ""
            if exc.code in EXPLAINED_ABORTS:
                try:
                    reason = self.node.sdo.upload(*self.objects.last_refusal).decode("ascii", "replace")
                except (SdoAbortedError, SdoCommunicationError, can.CanError):
                    reason = ""
            detail = f": {reason}" if reason and reason != "none" else ""
            code = f"SDO abort 0x{exc.code:08x}, {text}"
            return CanicalError(f"{where}: device refused {what} ({code}){detail}")
        return CanicalError(f"{where}: CAN error while {what}: {exc}")

    def upload(self, key: tuple[int, int], what: str) -> bytes:
        try:
            return bytes(self.node.sdo.upload(*key))
        except (SdoAbortedError, SdoCommunicationError, can.CanError) as exc:
            raise self._fail(exc, what) from None

    def download(self, key: tuple[int, int], data: bytes, what: str) -> None:
        try:
            self.node.sdo.download(*key, data)
        except (SdoAbortedError, SdoCommunicationError, can.CanError) as exc:
            raise self._fail(exc, what) from None

    def read_uint(self, key: tuple[int, int], what: str) -> int:
        return int.from_bytes(self.upload(key, what), "little")

    def write_uint(self, key: tuple[int, int], value: int, size: int, what: str) -> None:
        self.download(key, int(value).to_bytes(size, "little"), what)

    # ---------------------------------------------------------------------------------------
    # What the device says about itself
    # ---------------------------------------------------------------------------------------

    def require_canical_objects(self) -> None:
        """Refuse, before anything is read or written, a node without canical's coefficient
        objects (a vendor's IMU): one line saying what the way for it is."""
        try:
            self.node.sdo.upload(*self.objects.active_banks)
        except SdoAbortedError as exc:
            if exc.code not in NOT_IN_DICTIONARY:
                return  # it has the object (a refusal is the device's own business)
        except (SdoCommunicationError, can.CanError) as exc:
            raise self._fail(exc, "reading its identity") from None
        else:
            return
        who = ""
        with contextlib.suppress(SdoAbortedError, SdoCommunicationError, can.CanError):
            vendor = int.from_bytes(self.node.sdo.upload(*IDENTITY_VENDOR), "little")
            product = int.from_bytes(self.node.sdo.upload(*IDENTITY_PRODUCT), "little")
            who = f" (vendor 0x{vendor:08x}, product 0x{product:08x})"
        raise NotCanicalDevice(
            f"node 0x{self.node_id:02x}{who}: this IMU does not carry canical's coefficient objects "
            f"(0x{self.objects.active_banks[0]:04x} not in its dictionary); the way for it is "
            f"`canical serve` with set files (axes.AXIS.coefficients), which corrects its frames on the bus")

    def serial(self) -> int:
        return self.read_uint(self.objects.serial, "reading the serial number (0x1018 sub 4)")

    def limits(self) -> DeviceLimits:
        serial = self.serial()
        ranges = {}
        for axis, key in self.objects.rated_range.items():
            raw = self.upload(key, f"reading the rated range of axis {axis}")
            ranges[axis] = struct.unpack("<f", raw[:4])[0]
        capacity = self.read_uint(self.objects.capacity, "reading the coefficient bank capacity")
        return DeviceLimits(serial, ranges, capacity)

    def active(self) -> dict[str, str | None]:
        value = self.read_uint(self.objects.active_banks, "reading the active banks")
        try:
            return unpack_active(value)
        except ValueError as exc:
            raise CanicalError(f"node 0x{self.node_id:02x}: {exc}") from None

    def active_coupling(self) -> str | None:
        """The active coupling bank (None: no coupling, the identity)."""
        value = self.read_uint(self.objects.active_banks, "reading the active banks")
        try:
            return unpack_coupling(value)
        except ValueError as exc:
            raise CanicalError(f"node 0x{self.node_id:02x}: {exc}") from None

    def active_imu_set_id(self) -> int:
        return self.read_uint(self.objects.active_imu_set_id, "reading the active IMU set id")

    def active_ids(self) -> dict[str, int]:
        return {
            a: self.read_uint(key, f"reading the active set id of axis {a}")
            for a, key in self.objects.active_set_id.items()
        }

    def status(self) -> DeviceStatus:
        stored = self.read_uint(self.objects.stored_state, "reading the stored state")
        return DeviceStatus(
            serial=self.serial(),
            active=self.active(),
            active_ids=self.active_ids(),
            stored=unpack_active(stored),
            activations=self.read_uint(self.objects.activation_count, "reading the activation count"),
            coupling=self.active_coupling(),
            imu_set_id=self.active_imu_set_id(),
            stored_coupling=unpack_coupling(stored),
        )

    def bank(self, axis: str, bank: str) -> tuple[bytes, int, int]:
        """(content, CRC, status) of one bank."""
        ref = self.objects.bank(axis, bank)
        name = f"bank {axis.upper()} {bank}"
        status = self.read_uint((ref.index, ref.status), f"reading the status of {name}")
        content = b"" if status == 0 else self.upload((ref.index, ref.content), f"uploading {name}")
        crc = self.read_uint((ref.index, ref.crc), f"reading the CRC of {name}")
        return content, crc, status

    def signature(self, axis: str | None, bank: str) -> bytes:
        """The "Signature" bytes of an axis bank (``axis`` None: of coupling bank ``bank``)."""
        if axis is None:
            ref: BankRef | CouplingBankRef = self.objects.coupling_bank(bank)
            name = f"coupling bank {bank}"
        else:
            ref, name = self.objects.bank(axis, bank), f"bank {axis.upper()} {bank}"
        try:
            return bytes(self.node.sdo.upload(ref.index, ref.signature))
        except SdoAbortedError as exc:
            if exc.code in NO_SIGNATURE:
                return b""  # an empty Signature (unsigned), or a device without the sub-index
            raise self._fail(exc, f"reading the signature of {name}") from None
        except (SdoCommunicationError, can.CanError) as exc:
            raise self._fail(exc, f"reading the signature of {name}") from None

    def coupling_bank(self, bank: str) -> tuple[CouplingPayload, int]:
        """(content, CRC, IMU set id) and status of one coupling bank."""
        ref = self.objects.coupling_bank(bank)
        name = f"coupling bank {bank}"
        status = self.read_uint((ref.index, ref.status), f"reading the status of {name}")
        content = b"" if status == 0 else self.upload((ref.index, ref.content), f"uploading {name}")
        crc = self.read_uint((ref.index, ref.crc), f"reading the CRC of {name}")
        imu_set_id = self.read_uint((ref.index, ref.imu_set_id), f"reading the IMU set id of {name}")
        return CouplingPayload(content, crc, imu_set_id), status


@dataclass(frozen=True)
class DeviceStatus:
    serial: int
    active: dict[str, str | None]
    active_ids: dict[str, int]
    stored: dict[str, str | None]
    activations: int
    coupling: str | None = None
    imu_set_id: int = 0
    stored_coupling: str | None = None

    def describe(self) -> str:
        parts = []
        for axis in AXES:
            bank = self.active[axis]
            ident = f"0x{self.active_ids[axis]:08x} (bank {bank})"
            parts.append(f"{axis} none" if bank is None else f"{axis} {ident}")
        if self.coupling is not None:
            parts.append(f"coupling of IMU set 0x{self.imu_set_id:08x} (bank {self.coupling})")
        stored = self.stored == self.active and self.stored_coupling == self.coupling
        same = "stored for power-up" if stored else "NOT stored: a power cycle reverts"
        return ", ".join(parts) + f"; {same}"


@dataclass(frozen=True)
class AxisPlan:
    """What a push does on one axis."""

    axis: str
    source: str
    set_id: int
    content: bytes
    bank: str
    was_bank: str | None
    was_id: int
    signature: bytes = b""  # the bank's "Signature" (empty: an unsigned set)

    @property
    def unchanged(self) -> bool:
        return self.was_bank is not None and self.was_id == self.set_id


@dataclass(frozen=True)
class CouplingPlan:
    """What a push of an IMU set does with its coupling."""

    source: str
    payload: CouplingPayload
    bank: str
    was_bank: str | None
    was_id: int
    signature: bytes = b""  # the IMU set's signature (empty: unsigned)

    @property
    def imu_set_id(self) -> int:
        return self.payload.imu_set_id

    @property
    def unchanged(self) -> bool:
        return self.was_bank is not None and self.was_id == self.imu_set_id


@dataclass(frozen=True)
class PushPlan:
    node_id: int
    serial: int
    axes: tuple[AxisPlan, ...]
    selector_before: int
    selector_after: int
    coupling: CouplingPlan | None = None

    def describe(self) -> list[str]:
        lines = []
        c = self.coupling
        if c is not None:
            was = "no coupling" if c.was_bank is None else f"bank {c.was_bank} IMU set 0x{c.was_id:08x}"
            if c.unchanged:
                lines.append(f"  IMU set 0x{c.imu_set_id:08x} already active (coupling bank {c.was_bank})")
            else:
                lines.append(f"  IMU set 0x{c.imu_set_id:08x}: coupling {len(c.payload.content):5d} bytes -> "
                             f"coupling bank {c.bank} (active now: {was})  from {c.source}"
                             f"{_signed(c.signature)}")
        for p in self.axes:
            was = "no set" if p.was_bank is None else f"bank {p.was_bank} 0x{p.was_id:08x}"
            if p.unchanged:
                lines.append(f"  {p.axis}  set 0x{p.set_id:08x} already active (bank {p.was_bank})")
            else:
                lines.append(f"  {p.axis}  set 0x{p.set_id:08x} {len(p.content):5d} bytes -> bank {p.bank} "
                             f"(active now: {was})  from {p.source}{_signed(p.signature)}")
        lines.append(f"  selector 0x{self.selector_before:02x} -> 0x{self.selector_after:02x} (one write)")
        return lines


def _signed(signature: bytes) -> str:
    """What a plan line adds for a signed bank: its version (the first 8 bytes, little-endian)."""
    return f", signed as version {int.from_bytes(signature[:8], 'little')}" if signature else ""


@dataclass(frozen=True)
class DeviceCoupling:
    """The device's coupling state a push plans against: the active bank (None: identity) and id."""

    bank: str | None = None
    imu_set_id: int = 0


def plan_push(
    sets: Mapping[str, tuple[str, CoefficientSet]],
    limits: DeviceLimits,
    active: Mapping[str, str | None],
    active_ids: Mapping[str, int],
    node_id: int,
    imu: tuple[str, ImuSet] | None = None,
    coupling: DeviceCoupling = DeviceCoupling(),
    signatures: Mapping[str, bytes] | None = None,
) -> PushPlan:
    """Which bank each set goes to, and the selector that activates them; refuses inadmissible sets.

    ``sets`` maps axis → (where the set came from, the set); ``imu`` (where from, the IMU set) adds
    its coupling (``sets`` then holds its three axes); ``signatures`` the banks' signatures by axis
    (``"imu"``: the IMU set's, for its coupling bank). Pure: the device's state is passed in.
    """
    signatures = signatures or {}
    axes = []
    after = dict(active)
    for axis in AXES:
        if axis not in sets:
            continue
        source, cset = sets[axis]
        problem = admission_problem(cset, axis, limits)
        if problem:
            raise CanicalError(f"{source}: not for this device (node 0x{node_id:02x}): {problem}")
        content, crc = encode_set(cset)
        was = active.get(axis)
        plan = AxisPlan(axis, source, crc, content, other_bank(was), was, int(active_ids.get(axis, 0)),
                        signatures.get(axis, b""))
        if not plan.unchanged:
            after[axis] = plan.bank
        axes.append(plan)
    coupling_after = coupling.bank
    coupling_plan = None
    if imu is not None:
        source, imu_set = imu
        serial = sensor_id_for_serial(limits.serial)
        if imu_set.sensor_id != serial:
            raise CanicalError(f"{source}: not for this device (node 0x{node_id:02x}): IMU set for sensor "
                               f"{imu_set.sensor_id!r}, the device is serial {serial}")
        coupling_plan = CouplingPlan(source, encode_coupling(imu_set), other_bank(coupling.bank),
                                     coupling.bank, coupling.imu_set_id, signatures.get("imu", b""))
        size = len(coupling_plan.payload.content)
        if limits.bank_capacity is not None and size > limits.bank_capacity:
            raise CanicalError(f"{source}: not for this device (node 0x{node_id:02x}): its coupling is "
                               f"{size} bytes, the device's banks hold {limits.bank_capacity}")
        if not coupling_plan.unchanged:
            coupling_after = coupling_plan.bank
    elif coupling.bank is not None and any(not p.unchanged for p in axes):
        raise CanicalError(f"node 0x{node_id:02x} runs IMU set 0x{coupling.imu_set_id:08x}: its coupling "
                           "belongs to its three axes, so one axis cannot be replaced under it; push an "
                           "IMU set (canical push imu.yaml)")
    return PushPlan(node_id, limits.serial, tuple(axes), pack_active(dict(active), coupling.bank),
                    pack_active(after, coupling_after), coupling_plan)


@dataclass
class PushResult:
    plan: PushPlan
    status: DeviceStatus
    timings_s: dict[str, float] = field(default_factory=dict)
    bytes_written: int = 0


Progress = Callable[[str], None]


def push_sets(
    client: ImuClient,
    sets: Mapping[str, tuple[str, CoefficientSet]],
    *,
    imu: tuple[str, ImuSet] | None = None,
    dry_run: bool = False,
    progress: Progress = lambda _: None,
    signatures: Mapping[str, bytes] | None = None,
) -> PushResult | PushPlan:
    """Push sets, or an IMU set (``imu``: where from, the set; ``sets`` then empty), to the device
    (see module doc), with their signatures (see :func:`plan_push`); with ``dry_run`` only the
    plan, nothing written."""
    t0 = time.perf_counter()
    limits = client.limits()
    if imu is not None:
        if sets:
            raise CanicalError("an IMU set is pushed alone: its three axes are in it")
        sets = {c.axis: (f"{imu[0]} axes.{c.axis}", c) for c in imu[1].axes}
    coupling = DeviceCoupling(client.active_coupling(), client.active_imu_set_id())
    plan = plan_push(sets, limits, client.active(), client.active_ids(), client.node_id, imu, coupling,
                     signatures)
    if dry_run:
        return plan
    timings: dict[str, float] = {"read_state": time.perf_counter() - t0}
    token = secrets.randbits(32) | 1
    o = client.objects
    client.write_uint(o.download_lock, token, 4, "taking the download lock (another push running?)")
    silent = False
    written = 0
    try:
        t = time.perf_counter()
        for p in plan.axes:
            if p.unchanged:
                continue
            ref = o.bank(p.axis, p.bank)
            name = f"bank {p.axis.upper()} {p.bank}"
            progress(f"downloading {len(p.content)} bytes to {name}")
            client.download((ref.index, ref.content), p.content, f"downloading {name}")
            client.write_uint((ref.index, ref.crc), p.set_id, 4, f"writing the CRC of {name}")
            if p.signature:
                client.download((ref.index, ref.signature), p.signature, f"writing the signature of {name}")
            written += len(p.content) + 4 + len(p.signature)
        written += _download_coupling(client, plan.coupling, progress)
        timings["download"] = time.perf_counter() - t
        t = time.perf_counter()
        for p in plan.axes:
            if p.unchanged:
                continue
            content, crc, bank_status = client.bank(p.axis, p.bank)
            name = f"bank {p.axis.upper()} {p.bank}"
            signature = client.signature(p.axis, p.bank) if p.signature else b""
            if content != p.content or crc != p.set_id or signature != p.signature:
                raise CanicalError(f"node 0x{client.node_id:02x}: read-back of {name} differs from what was "
                                   f"written (another writer on the bus?); nothing activated")
            if bank_status != STATUS_VALID:
                raise CanicalError(f"node 0x{client.node_id:02x}: device reports {name} "
                                   f"{STATUS_TEXT.get(bank_status, bank_status)}; nothing activated")
        _verify_coupling(client, plan.coupling)
        timings["verify"] = time.perf_counter() - t
        t = time.perf_counter()
        if plan.selector_after != plan.selector_before:
            progress(f"activating: selector 0x{plan.selector_after:02x}")
            client.write_uint(o.active_banks, plan.selector_after, 1, "activating the new banks")
        timings["activate"] = time.perf_counter() - t
        t = time.perf_counter()
        client.write_uint(o.store, STORE_SIGNATURE, 4, "storing (0x1010)")
        timings["store"] = time.perf_counter() - t
        status = client.status()
    except DeviceSilent:
        silent = True
        raise
    finally:
        if not silent:
            with contextlib.suppress(CanicalError):  # the lease expires on the device anyway
                client.write_uint(o.download_lock, 0, 4, "releasing the download lock")
    timings["total"] = time.perf_counter() - t0
    for p in plan.axes:
        if status.active_ids[p.axis] != p.set_id:
            raise CanicalError(f"node 0x{client.node_id:02x}: after the push axis {p.axis} runs "
                               f"0x{status.active_ids[p.axis]:08x}, not 0x{p.set_id:08x} (another writer?)")
    if plan.coupling is not None and status.imu_set_id != plan.coupling.imu_set_id:
        raise CanicalError(f"node 0x{client.node_id:02x}: after the push the device applies the coupling of "
                           f"IMU set 0x{status.imu_set_id:08x}, not 0x{plan.coupling.imu_set_id:08x} "
                           "(another writer?)")
    return PushResult(plan, status, timings, written)


def _download_coupling(client: ImuClient, plan: CouplingPlan | None, progress: Progress) -> int:
    """Write an IMU set's coupling bank (inactive: nothing the device runs changes); bytes written."""
    if plan is None or plan.unchanged:
        return 0
    ref = client.objects.coupling_bank(plan.bank)
    name = f"coupling bank {plan.bank}"
    progress(f"downloading {len(plan.payload.content)} bytes to {name}")
    client.download((ref.index, ref.content), plan.payload.content, f"downloading {name}")
    client.write_uint((ref.index, ref.crc), plan.payload.crc, 4, f"writing the CRC of {name}")
    client.write_uint((ref.index, ref.imu_set_id), plan.imu_set_id, 4, f"writing the IMU set id of {name}")
    if plan.signature:
        client.download((ref.index, ref.signature), plan.signature, f"writing the signature of {name}")
    return len(plan.payload.content) + 8 + len(plan.signature)


def _verify_coupling(client: ImuClient, plan: CouplingPlan | None) -> None:
    """Read the coupling bank back: the bytes written, and valid on its own as the device sees it."""
    if plan is None or plan.unchanged:
        return
    back, bank_status = client.coupling_bank(plan.bank)
    name = f"coupling bank {plan.bank}"
    signature = client.signature(None, plan.bank) if plan.signature else b""
    if back != plan.payload or signature != plan.signature:
        raise CanicalError(f"node 0x{client.node_id:02x}: read-back of {name} differs from what was "
                           f"written (another writer on the bus?); nothing activated")
    if bank_status != STATUS_VALID:
        raise CanicalError(f"node 0x{client.node_id:02x}: device reports {name} "
                           f"{STATUS_TEXT.get(bank_status, bank_status)}; nothing activated")


def pull_sets(client: ImuClient, axes: tuple[str, ...] = AXES) -> dict[str, CoefficientSet]:
    """The device's active sets for ``axes`` (those that have one), each verified three ways."""
    client.require_canical_objects()
    active = client.active()
    ids = client.active_ids()
    out = {}
    for axis in axes:
        bank = active[axis]
        if bank is None:
            continue
        content, crc, _ = client.bank(axis, bank)
        where = f"node 0x{client.node_id:02x} bank {axis.upper()} {bank}"
        if crc != ids[axis]:
            raise CanicalError(f"{where}: CRC 0x{crc:08x} is not the active set id 0x{ids[axis]:08x}")
        cset = decode_set(content, crc, where)
        if cset.axis != axis:
            raise CanicalError(f"{where}: holds a set for axis {cset.axis}")
        out[axis] = cset
    return out


def pull_imu_set(client: ImuClient) -> ImuSet:
    """The IMU set the device runs: its three active axes and its active coupling bank, accepted
    only if together they make the IMU set the device's "Active IMU set id" names."""
    client.require_canical_objects()
    bank = client.active_coupling()
    where = f"node 0x{client.node_id:02x}"
    if bank is None:
        raise CanicalError(f"{where}: runs no IMU set (no coupling active); `canical pull` without "
                           "--imu-set reads its single-axis sets")
    imu_set_id = client.active_imu_set_id()
    sets = pull_sets(client)
    missing = [a for a in AXES if a not in sets]
    if missing:
        raise CanicalError(f"{where}: coupling active but no set for axis {', '.join(missing)}")
    payload, _ = client.coupling_bank(bank)
    source = f"{where} coupling bank {bank}"
    if payload.imu_set_id != imu_set_id:
        raise CanicalError(f"{source}: IMU set id 0x{payload.imu_set_id:08x} is not the active one "
                           f"0x{imu_set_id:08x}")
    envelope = decode_coupling(payload.content, payload.crc, source)
    return join_imu_set(envelope, tuple(sets[a] for a in AXES), imu_set_id, source)


def active_signatures(client: ImuClient, axes: tuple[str, ...] = (), *,
                      imu: bool = False) -> dict[str, bytes]:
    """The "Signature" bytes of the active banks of ``axes``, or (``imu``) of the active coupling
    bank under ``"imu"``: what a verifier checks the pulled sets against."""
    if imu:
        bank = client.active_coupling()
        return {} if bank is None else {"imu": client.signature(None, bank)}
    active = client.active()
    return {a: client.signature(a, active[a]) for a in axes if active[a] is not None}  # type: ignore[arg-type]


@dataclass(frozen=True)
class ActiveOnDevice:
    """What a device runs: its IMU set when a coupling is active (``imu``), else its single-axis sets."""

    sets: dict[str, CoefficientSet]
    imu: ImuSet | None = None
    #: the banks' "Signature" bytes: by axis, or ``"imu"`` (the coupling bank's) for an IMU set
    signatures: dict[str, bytes] = field(default_factory=dict)


def pull_active(network: canopen.Network, node_id: int, axes: tuple[str, ...] = AXES,
                timeout: float = DEFAULT_TIMEOUT_S) -> ActiveOnDevice:
    """The sets a device runs, whole: its IMU set (axes and coupling) when it runs one, for a
    caller with its own network (the daemon at start and on SIGHUP)."""
    client = ImuClient(network, node_id, timeout)
    try:
        client.require_canical_objects()
        if tuple(axes) == AXES and client.active_coupling() is not None:
            imu = pull_imu_set(client)
            return ActiveOnDevice({}, imu, active_signatures(client, imu=True))
        sets = pull_sets(client, axes)
        return ActiveOnDevice(sets, None, active_signatures(client, tuple(sets)))
    finally:
        client.close()
