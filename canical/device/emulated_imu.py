"""An emulated IMU node: the canical IMU's object dictionary served by a canopen LocalNode.

It is what a real sensor would be to the rest of canical, on any python-can
interface: it transmits the raw TPDOs (IMU_RAW, IMU_AUX; TABLE_REF too when it
sits on a simulated rate table) from :mod:`canical.sim.imu_stream`, answers SDO
on its object dictionary (:mod:`canical.imu_dictionary`), keeps its
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
"""

from __future__ import annotations

import logging
import os
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING

import canopen
from canopen.sdo import SdoAbortedError

from canical.device.coefficient_banks import BankRefusal, BankStore
from canical.frames.imu_frames import CHANNELS, ImuFrames, set_tag
from canical.imu_dictionary import (
    ABORT_VALUE_RANGE,
    AXES,
    RESTORE_SIGNATURE,
    STORE_SIGNATURE,
    imu_objects,
    object_dictionary,
    unpack_active,
)
from canical.sets.admission import DeviceLimits
from canical.sets.corrector import Corrector

if TYPE_CHECKING:
    from canical.device.firmware_eval import FirmwareCorrector

log = logging.getLogger("canical.imu")

MAX_LAG_S = 0.5  # behind schedule by more than this: skip ahead rather than burst


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

    def __init__(self, config: EmulatorConfig, network: canopen.Network) -> None:
        self.config = config
        self.network = network
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
        self.node.add_read_callback(self._on_read)
        self.node.add_write_callback(self._on_write)
        self._bank_at = {(b.index, b.content): k for k, b in o.banks.items()}
        self._crc_at = {(b.index, b.crc): k for k, b in o.banks.items()}
        self._status_at = {(b.index, b.status): k for k, b in o.banks.items()}
        self._size_at = {(b.index, b.size): k for k, b in o.banks.items()}
        self._id_at = {v: a for a, v in o.active_set_id.items()}
        self.stop_event = threading.Event()
        self.frames_sent = 0
        network.add_node(self.node)

    # ---------------------------------------------------------------------------------------
    # SDO
    # ---------------------------------------------------------------------------------------

    def _on_read(self, index: int, subindex: int, od) -> object | None:
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
        if key in self._id_at:
            return s.active_id(self._id_at[key])
        simple = {
            o.active_banks: s.active_value,
            o.activation_count: lambda: s.activation_count,
            o.last_refusal: lambda: s.last_refusal,
            o.download_lock: s.current_lock,
            o.correction_mode: lambda: int(self.correction),
            o.stored_state: s.stored_value,
        }
        getter = simple.get(key)
        return getter() if getter else None

    def _on_write(self, index: int, subindex: int, od, data: bytes) -> None:
        key = (index, subindex)
        s, o = self.store, self.objects
        try:
            if key in self._bank_at:
                s.write_content(*self._bank_at[key], bytes(data))
            elif key in self._crc_at:
                s.write_crc(*self._crc_at[key], int.from_bytes(data, "little"))
            elif key == o.active_banks:
                s.activate(data[0])
            elif key == o.store:
                s.store(int.from_bytes(data, "little") == STORE_SIGNATURE)
            elif key == o.restore:
                s.restore_defaults(int.from_bytes(data, "little") == RESTORE_SIGNATURE)
            elif key == o.download_lock:
                s.take_lock(int.from_bytes(data, "little"))
            elif key == o.correction_mode:
                if data[0] > 1:
                    raise BankRefusal(ABORT_VALUE_RANGE, f"correction mode {data[0]}: 0 or 1")
                self.correction = bool(data[0])
                log.info("on-device correction %s", "on" if self.correction else "off")
        except BankRefusal as exc:
            raise SdoAbortedError(exc.code) from None

    # ---------------------------------------------------------------------------------------
    # Transmit loop
    # ---------------------------------------------------------------------------------------

    def boot_up(self) -> None:
        """The CANopen boot-up message, then the active sets in the log."""
        self.network.send_message(0x700 + self.config.node_id, b"\x00")
        active = unpack_active(self.store.active_value())
        log.info(
            "node 0x%02x serial %d up; active %s",
            self.config.node_id, self.config.serial,
            " ".join(f"{a}={b or 'none'}:0x{self.store.active_id(a):08x}" for a, b in active.items()),
        )

    def run(self, duration_s: float | None = None) -> None:
        """Transmit until :attr:`stop_event` is set (or ``duration_s`` wall seconds passed)."""
        if self.config.stream is None:
            self.stop_event.wait(duration_s)
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
        send = self.network.send_message
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
                if table_frames is not None and self.config.table_ref:
                    ft, fw, fs = table_frames
                    while j < len(ft) and ft[j] <= t:
                        send(*frames.table(fw[j], axis, fs[j], j))
                        j += 1
                if kept is not None and not kept[i]:
                    continue  # the sample's frames are lost (a logger or bus overload drops a burst)
                counts = (raw["x"][i], raw["y"][i], raw["z"][i])
                aux_id, aux_data = frames.aux(supply, t, k)
                raw_id, raw_data = frames.raw(counts, temp, k)
                send(aux_id, aux_data)
                send(raw_id, raw_data)
                if self.config.table_ref and table_frames is None:
                    send(*frames.table(w, axis, settled, k))
                self.frames_sent += 1
                if not self.correction:
                    continue
                if self.store.generation != generation:
                    generation = self.store.generation
                    correctors = self.device_correctors()
                    tag = set_tag({a: self.store.active_id(a) for a in AXES})
                send(*self._corrected(correctors, tag, raw_id, raw_data, aux_id, aux_data, k))

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

    def _corrected(self, correctors, tag, raw_id, raw_data, aux_id, aux_data, k):
        """IMU_RATE for one sample, from the frames exactly as a receiver decodes them."""
        rv = self.frames.decode(raw_id, raw_data).values
        av = self.frames.decode(aux_id, aux_data).values
        inputs = {CHANNELS[n]: float(v) for n, v in (*rv.items(), *av.items()) if n in CHANNELS}
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
        return self.frames.rate(rates, oos, unc, tag, k)


def _entry(od: canopen.ObjectDictionary, key: tuple[int, int]):
    obj = od[key[0]]
    return obj if isinstance(obj, canopen.objectdictionary.ODVariable) else obj[key[1]]


def _set_default(od: canopen.ObjectDictionary, key: tuple[int, int], value: object) -> None:
    _entry(od, key).default = value


def state_path_default(serial: int) -> Path:
    """Where a device keeps its banks unless told otherwise."""
    base = Path(os.environ.get("XDG_STATE_HOME", Path.home() / ".local" / "state"))
    return base / "canical" / f"imu-{serial}.json"
