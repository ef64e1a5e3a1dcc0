"""An emulated IMU node: the canical IMU's object dictionary served by a canopen LocalNode.

It is what a real sensor would be to the rest of canical, on any python-can
interface: it transmits the raw TPDOs (IMU_RAW, IMU_AUX; TABLE_REF too when it
sits on a simulated rate table) from :mod:`canical.sim.imu_stream`, answers SDO
on its object dictionary (:mod:`canical.frames.imu_dictionary`), keeps its
coefficient banks by the rules of :mod:`canical.device.coefficient_banks` in a state
file so a restart (a power cycle) keeps what was stored, and on request
(object "Correction mode" = 1) corrects its own raw samples with its active
sets and transmits them as IMU_RATE (TPDO3): on-device correction, to check
the daemon and the device against each other. It corrects with the firmware's own
C evaluator (``firmware/canical_eval.c`` through :mod:`canical.device.firmware_eval`), so
the bus tests run the code a sensor would; where that library cannot be built, or
does not evaluate a set (a term kind newer than it), the Python evaluator takes
over with a log line.

Correction inputs are taken from the device's own frames as a receiver decodes
them (temperature in 0.1 degC, supply in mV, uptime in ms), so the device, the
daemon and ``canical apply`` on a recording of the bus see the same numbers.

The bus going away (vcan0 set down, bus-off, unplugged) is ridden out as the daemon
rides it out (:class:`canical.bus_outage.Outage`: one line when it starts, once a minute while
it lasts, one when it ends; capped back-off between attempts): a failed send or a failed
receive reopens the bus after the back-off and the programme carries on from where the
clock is, so a service manager never sees a traceback for what is not a bug.
"""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import can
import canopen
from canopen.sdo import SdoAbortedError

from canical.bus_outage import OUTAGE_LOG_EVERY_S, REOPEN_BACKOFF_S, Outage
from canical.device.coefficient_banks import BankRefusal, BankStore
from canical.errors import CanicalError
from canical.frames.imu_dictionary import (
    ABORT_VALUE_RANGE,
    AXES,
    PROVISIONING_CLOSED,
    PROVISIONING_OPEN,
    RESTORE_SIGNATURE,
    STORE_SIGNATURE,
    imu_objects,
    object_dictionary,
    unpack_active,
)
from canical.frames.imu_frames import CHANNELS, ImuFrames, set_tag
from canical.sets.admission import DeviceLimits
from canical.sets.corrector import Corrector

if TYPE_CHECKING:
    from collections.abc import Callable

    from canical.device.firmware_eval import FirmwareCorrector, FirmwareImuCorrector
    from canical.sets.imu_set import Matrix

log = logging.getLogger("canical.imu")

MAX_LAG_S = 0.5  # behind schedule by more than this: skip ahead rather than burst
RX_ERROR_PAUSE_S = 0.05  # a receive error is noted, then the receive thread pauses this long
BUS_ERRORS = (can.CanError, OSError)  # what a send raises when the interface is gone


@dataclass(frozen=True)
class EmulatorConfig:
    """How the emulated device is built; ``stream=None`` answers SDO only."""

    node_id: int = 0x10
    serial: int = 4711
    state_path: Path | None = None
    rated_range_dps: dict[str, float] = field(default_factory=lambda: dict.fromkeys(AXES, 50.0))
    stream: object | None = None  # canical.sim.imu_stream.StreamConfig (imported only when streaming)
    speed: float = 1.0  # simulated seconds per wall-clock second
    table_ref: bool = True
    correction: bool = False
    dbc_path: Path | None = None


class EmulatedImu:
    """The device: object dictionary, bank store, and (optionally) its transmit loop."""

    def __init__(self, config: EmulatorConfig, network: canopen.Network, *,
                 reopen: Callable[[], None] | None = None, bus_name: str = "CAN bus") -> None:
        """``reopen`` connects ``network`` afresh after an outage (raising
        :class:`CanicalError` when it cannot); without it a lost bus is only retried."""
        self.config = config
        self.network = network
        self.reopen = reopen
        self.bus_name = bus_name
        self.outage: Outage | None = None
        self.rx_errors = receive_errors(network)
        self.objects = imu_objects()
        od = object_dictionary(config.node_id)
        o = self.objects
        _set_default(od, o.serial, config.serial)
        for axis, (index, sub) in o.rated_range.items():
            _set_default(od, (index, sub), float(config.rated_range_dps.get(axis, 0.0)))
        capacity = int(_entry(od, o.capacity).default)
        limits = DeviceLimits(config.serial, dict(config.rated_range_dps))
        self.store = BankStore.boot(limits, capacity, config.state_path)
        self.correction = bool(config.correction)
        self.frames = ImuFrames(config.node_id, config.dbc_path)
        self.node = canopen.LocalNode(config.node_id, od)
        self.node.add_read_callback(self._on_read)  # type: ignore[no-untyped-call]  # canopen: untyped
        self.node.add_write_callback(self._on_write)  # type: ignore[no-untyped-call]
        self._bank_at = {(b.index, b.content): k for k, b in o.banks.items()}
        self._crc_at = {(b.index, b.crc): k for k, b in o.banks.items()}
        self._status_at = {(b.index, b.status): k for k, b in o.banks.items()}
        self._size_at = {(b.index, b.size): k for k, b in o.banks.items()}
        self._signature_at = {(b.index, b.signature): k for k, b in o.banks.items()}
        self._id_at = {v: a for a, v in o.active_set_id.items()}
        self._coupling_at = {(c.index, sub): (c.bank, what) for c in o.coupling_banks.values()
                             for sub, what in ((c.content, "content"), (c.crc, "crc"), (c.status, "status"),
                                               (c.size, "size"), (c.imu_set_id, "imu_set_id"),
                                               (c.signature, "signature"))}
        self.stop_event = threading.Event()
        #: the active IMU set's coupling as the device runs it: the C evaluator's three-axis
        #: sample, or the matrix applied in Python (where the C library cannot); None: identity
        self.coupled: FirmwareImuCorrector | Matrix | None = None
        network.add_node(self.node)

    # ---------------------------------------------------------------------------------------
    # The bus going away
    # ---------------------------------------------------------------------------------------

    def send(self, can_id: int, data: bytes) -> bool:
        """Send one frame, riding out a bus outage first; False when asked to stop meanwhile."""
        while True:
            try:
                self.network.send_message(can_id, data)
            except BUS_ERRORS as exc:
                if not self.ride_out(f"send: {exc}"):
                    return False
                continue
            if self.outage is not None:
                self._end_outage()
            return True

    def ride_out(self, why: str) -> bool:
        """The bus failed: log it (once per outage), wait the back-off, reopen the bus.

        Returns False when a stop was asked for while waiting.
        """
        now = time.monotonic()
        if self.outage is None:
            self.outage = Outage(now, why)
            log.warning("%s lost: %s; retrying with back-off up to %.0f s", self.bus_name, why,
                        REOPEN_BACKOFF_S[-1])
        else:
            self.outage.reason = why
            if now >= self.outage.next_log:
                self.outage.next_log = now + OUTAGE_LOG_EVERY_S
                log.warning("%s still down after %.0f s (%d attempts): %s", self.bus_name,
                            now - self.outage.since, self.outage.attempts, why)
        if self.stop_event.wait(self.outage.delay()):
            return False
        self.rx_errors.failed.clear()
        if self.reopen is not None:
            try:
                self.reopen()
            except CanicalError as exc:
                self.outage.reason = str(exc)
        return not self.stop_event.is_set()

    def _end_outage(self) -> None:
        outage, self.outage = self.outage, None
        assert outage is not None
        log.info("%s back after %.1f s down (%d attempts)", self.bus_name, time.monotonic() - outage.since,
                 outage.attempts)

    # ---------------------------------------------------------------------------------------
    # SDO
    # ---------------------------------------------------------------------------------------

    def _on_read(self, index: int, subindex: int, od: object) -> object | None:
        key = (index, subindex)
        s, o = self.store, self.objects
        if key in self._bank_at:
            return s.banks[self._bank_at[key]].content
        if key in self._crc_at:
            return s.banks[self._crc_at[key]].crc
        if key in self._status_at:
            return s.check(*self._status_at[key]).status
        if key in self._size_at:
            return len(s.banks[self._size_at[key]].content)
        if key in self._signature_at:
            return s.banks[self._signature_at[key]].signature
        if key in self._id_at:
            return s.active_id(self._id_at[key])
        if key in self._coupling_at:
            bank, what = self._coupling_at[key]
            b = s.coupling[bank]
            if what == "status":
                return s.check_coupling(bank).status
            values = {"content": b.content, "crc": b.crc, "size": len(b.content), "imu_set_id": b.imu_set_id,
                      "signature": b.signature}
            return values[what]
        simple: dict[tuple[int, int], Callable[[], object]] = {
            o.active_imu_set_id: s.active_imu_set_id,
            o.active_banks: s.active_value,
            o.activation_count: lambda: s.activation_count,
            o.last_refusal: lambda: s.last_refusal,
            o.download_lock: s.current_lock,
            o.correction_mode: lambda: int(self.correction),
            o.stored_state: s.stored_value,
            o.trust_key: lambda: s.trust.key,
            o.provisioning: lambda: PROVISIONING_OPEN if s.trust.provisioning_open else PROVISIONING_CLOSED,
            o.rollback_counter: lambda: s.trust.counter,
        }
        getter = simple.get(key)
        return getter() if getter else None

    def _on_write(self, index: int, subindex: int, od: object, data: bytes) -> None:
        key = (index, subindex)
        s, o = self.store, self.objects
        try:
            if key in self._bank_at:
                s.write_content(*self._bank_at[key], bytes(data))
            elif key in self._crc_at:
                s.write_crc(*self._crc_at[key], int.from_bytes(data, "little"))
            elif key in self._signature_at:
                s.write_signature(*self._signature_at[key], bytes(data))
            elif key in self._coupling_at:
                self._write_coupling(*self._coupling_at[key], bytes(data))
            elif key == o.active_banks:
                s.activate(data[0])
            elif key == o.store:
                s.store(int.from_bytes(data, "little") == STORE_SIGNATURE)
            elif key == o.restore:
                s.restore_defaults(int.from_bytes(data, "little") == RESTORE_SIGNATURE)
            elif key == o.trust_key:
                s.write_trust_key(bytes(data))
            elif key == o.provisioning:
                s.close_provisioning(int.from_bytes(data, "little"))
            elif key == o.download_lock:
                s.take_lock(int.from_bytes(data, "little"))
            elif key == o.correction_mode:
                if data[0] > 1:
                    raise BankRefusal(ABORT_VALUE_RANGE, f"correction mode {data[0]}: 0 or 1")
                self.correction = bool(data[0])
                log.info("on-device correction %s", "on" if self.correction else "off")
        except BankRefusal as exc:
            raise SdoAbortedError(exc.code) from None

    def _write_coupling(self, bank: str, what: str, data: bytes) -> None:
        s = self.store
        if what == "content":
            s.write_coupling_content(bank, data)
        elif what == "crc":
            s.write_coupling_crc(bank, int.from_bytes(data, "little"))
        elif what == "imu_set_id":
            s.write_imu_set_id(bank, int.from_bytes(data, "little"))
        elif what == "signature":
            s.write_coupling_signature(bank, data)
        else:  # Status and Size are read-only in the EDS: canopen refuses them before this
            raise BankRefusal(ABORT_VALUE_RANGE, f"coupling bank {bank}: {what} is read-only")

    # ---------------------------------------------------------------------------------------
    # Transmit loop
    # ---------------------------------------------------------------------------------------

    def boot_up(self) -> None:
        """The CANopen boot-up message, then the active sets in the log."""
        if not self.send(0x700 + self.config.node_id, b"\x00"):
            return
        active = unpack_active(self.store.active_value())
        coupling = self.store.active_coupling
        log.info(
            "node 0x%02x serial %d up; active %s coupling=%s:0x%08x",
            self.config.node_id, self.config.serial,
            " ".join(f"{a}={b or 'none'}:0x{self.store.active_id(a):08x}" for a, b in active.items()),
            coupling or "none", self.store.active_imu_set_id(),
        )

    def run(self, duration_s: float | None = None) -> None:
        """Transmit until :attr:`stop_event` is set (or ``duration_s`` wall seconds passed)."""
        if self.config.stream is None:
            self._serve_sdo(duration_s)
            return
        from canical.sim.imu_stream import imu_blocks  # numpy/scipy only where streaming

        stream = self.config.stream
        period = 1.0 / (stream.sample_rate_hz * self.config.speed)  # type: ignore[attr-defined]
        start = time.perf_counter()
        deadline = None if duration_s is None else start + duration_s
        k = 0
        generation = -1
        correctors: dict[str, FirmwareCorrector | Corrector] = {}
        tag = 0
        send = self.send
        frames = self.frames
        axis = stream.table.axis  # type: ignore[attr-defined]
        for block in imu_blocks(stream):  # type: ignore[arg-type]
            raw = {a: block.raw[a].tolist() for a in AXES}
            ref = block.ref_dps if block.ref_dps is not None else block.table_rate_dps
            rows = zip(
                block.time_s.tolist(), ref.tolist(), block.settled.tolist(),
                block.temp_c.tolist(), block.supply_v.tolist(), strict=True,
            )
            kept = block.kept.tolist() if block.kept is not None else None
            # The table's own frames, on its own clock, sent as their time comes.
            table_frames = [f.tolist() for f in block.table_frames] if block.table_frames else None
            j = 0
            for i, (t, w, settled, temp, supply) in enumerate(rows):
                if self.stop_event.is_set():
                    return
                now = time.perf_counter()
                target = start + k * period
                if target > now:
                    if deadline is not None and target > deadline:
                        return
                    self.stop_event.wait(target - now)
                elif now - target > MAX_LAG_S:
                    start = now - k * period  # fell far behind (slow host): carry on from here
                k += 1
                if self.rx_errors.failed.is_set() and not self.ride_out(self.rx_errors.reason):
                    return
                if table_frames is not None and self.config.table_ref:
                    ft, fw, fs = table_frames
                    while j < len(ft) and ft[j] <= t:
                        if not send(*frames.table(fw[j], axis, fs[j], j)):
                            return
                        j += 1
                if kept is not None and not kept[i]:
                    continue  # the sample's frames are lost (a logger or bus overload drops a burst)
                counts = (raw["x"][i], raw["y"][i], raw["z"][i])
                aux_id, aux_data = frames.aux(supply, t, k)
                raw_id, raw_data = frames.raw(counts, temp, k)
                if not (send(aux_id, aux_data) and send(raw_id, raw_data)):
                    return
                with_ref = self.config.table_ref and table_frames is None
                if with_ref and not send(*frames.table(w, axis, settled, k)):
                    return
                if not self.correction:
                    continue
                if self.store.generation != generation:
                    generation = self.store.generation
                    correctors = self.device_correctors()
                    self.coupled = self.device_coupling()
                    tag = set_tag({a: self.store.active_id(a) for a in AXES})
                if not send(*self._corrected(correctors, tag, raw_id, raw_data, aux_id, aux_data, k)):
                    return

    def _serve_sdo(self, duration_s: float | None) -> None:
        """An SDO-only device: answer until stopped, reopening the bus when its receive fails."""
        end = None if duration_s is None else time.monotonic() + duration_s
        while not self.stop_event.is_set():
            left = None if end is None else end - time.monotonic()
            if left is not None and left <= 0:
                return
            if not self.rx_errors.failed.wait(0.5 if left is None else min(0.5, left)):
                if self.outage is not None:
                    self._end_outage()  # reopened and no receive error since
                continue
            if not self.ride_out(self.rx_errors.reason):
                return

    def device_correctors(self) -> dict[str, FirmwareCorrector | Corrector]:
        """The active sets as the device runs them: in the firmware's C evaluator
        (:mod:`canical.device.firmware_eval`), or in Python where it cannot (logged there)."""
        from canical.device.firmware_eval import (  # ctypes only when correcting
            FirmwareCorrector,
            corrector_for,
        )

        out: dict[str, FirmwareCorrector | Corrector] = {}
        for axis, cset in self.store.active_sets().items():
            c = corrector_for(cset, serial=self.config.serial, axis=axis,
                              rated_range_dps=float(self.config.rated_range_dps.get(axis, 0.0)))  # fmt: skip
            engine = "the firmware evaluator (C)" if isinstance(c, FirmwareCorrector) else "Python"
            log.info("axis %s: set 0x%08x corrected on the device with %s", axis, c.set_id, engine)
            out[axis] = c
        return out

    def device_coupling(self) -> FirmwareImuCorrector | Matrix | None:
        """The active IMU set's coupling as the device applies it to the three corrected rates:
        in the C evaluator with its three sets (``ce_eval3``), or the matrix for Python (logged
        there); None when no coupling is active (the identity)."""
        imu = self.store.active_imu_set()
        if imu is None:
            return None
        from canical.device.firmware_eval import FirmwareImuCorrector  # ctypes only when correcting

        try:  # spans were checked per axis on activation: not again here
            coupled: FirmwareImuCorrector | Matrix = FirmwareImuCorrector(imu, serial=self.config.serial)
            engine = "the firmware evaluator (C)"
        except CanicalError as exc:
            log.warning("IMU set coupling: applied in Python, not with the firmware evaluator: %s", exc)
            coupled, engine = imu.coupling, "Python"
        log.info("IMU set 0x%08x: coupling applied on the device with %s", self.store.active_imu_set_id(),
                 engine)
        return coupled

    def _corrected(self, correctors: dict[str, FirmwareCorrector | Corrector], tag: int, raw_id: int,
                   raw_data: bytes, aux_id: int, aux_data: bytes, k: int) -> tuple[int, bytes]:
        """IMU_RATE for one sample, from the frames exactly as a receiver decodes them."""
        raw_frame, aux_frame = self.frames.decode(raw_id, raw_data), self.frames.decode(aux_id, aux_data)
        assert raw_frame is not None and aux_frame is not None  # our own frames: always decoded
        rv, av = raw_frame.values, aux_frame.values
        inputs = {CHANNELS[n]: float(v) for n, v in (*rv.items(), *av.items()) if n in CHANNELS}
        coupled = self.coupled
        if coupled is not None and not isinstance(coupled, tuple):
            raw3 = [float(rv[f"GyroRaw{a.upper()}"]) for a in AXES]
            rates3, oos3 = coupled.correct_one(raw3, inputs)
            return self.frames.rate(rates3, oos3, [False] * 3, tag, k)
        rates, oos, unc = [], [], []
        for a in AXES:
            c = correctors.get(a)
            if c is None:
                rates.append(0.0)
                oos.append(False)
                unc.append(True)
                continue
            r, o = c.correct_one(float(rv[f"GyroRaw{a.upper()}"]), inputs)
            rates.append(r)
            oos.append(o)
            unc.append(False)
        if coupled is not None:  # the Python fallback: an active coupling means all three axes have sets
            rates = [sum(m * r for m, r in zip(row, rates, strict=True)) for row in coupled]
        return self.frames.rate(rates, oos, unc, tag, k)


class ReceiveErrors(can.Listener):
    """A python-can listener that notes a failed receive (a down interface) and handles it.

    Unhandled, the error ends python-can's receive thread with a traceback and no SDO is
    answered again; noted here, the device rides the outage out and reopens the bus. Give it to
    :func:`canical.device.can_network.open_network` (``listeners=``) so it is there before the first
    receive: a bus that is down from the start fails at once.
    """

    def __init__(self) -> None:
        self.failed = threading.Event()
        self.reason = ""

    def on_message_received(self, msg: can.Message) -> None:
        """Frames are canopen's (its own listener); only errors are ours."""

    def on_error(self, exc: Exception) -> None:
        self.reason = f"receive: {exc}"
        self.failed.set()
        time.sleep(RX_ERROR_PAUSE_S)  # a dead bus fails at once: do not spin on it

    def stop(self) -> None:
        """Nothing to release."""


def receive_errors(network: canopen.Network) -> ReceiveErrors:
    """The network's :class:`ReceiveErrors`, added (to later connections too) if it has none."""
    for existing in network.listeners:
        if isinstance(existing, ReceiveErrors):
            return existing
    listener = ReceiveErrors()
    # canopen types its list as its own MessageListener; the Notifier takes any can.Listener
    network.listeners.append(listener)  # type: ignore[arg-type]
    if network.notifier is not None:
        network.notifier.add_listener(listener)
    return listener


def _entry(od: canopen.ObjectDictionary, key: tuple[int, int]) -> Any:  # an ODVariable; its default any type
    obj = od[key[0]]
    return obj if isinstance(obj, canopen.objectdictionary.ODVariable) else obj[key[1]]


def _set_default(od: canopen.ObjectDictionary, key: tuple[int, int], value: object) -> None:
    _entry(od, key).default = value


def state_path_default(serial: int) -> Path:
    """Where a device keeps its banks unless told otherwise."""
    base = Path(os.environ.get("XDG_STATE_HOME", Path.home() / ".local" / "state"))
    return base / "canical" / f"imu-{serial}.json"
