"""The bus half of ``canical demo``: an emulated IMU, a session recorded from it, a download, live correction.

One function runs the whole loop the product exists for, on a CAN bus: python-can's
in-process ``virtual`` bus by default (no kernel support needed), or a real
interface such as vcan0 with the device emulated in this process or running on
its own (``canical emulate``):

1. the IMU streams raw frames while a simulated rate table steps through its
   programme (TABLE_REF on the bus), and it has an effect nobody declared: its
   bias drifts with die temperature;
2. one pass of the programme is recorded from the bus (the sensor id read from
   the device over SDO) and calibrated; the closed loop finds the undeclared effect;
3. the set is pushed to the device (inactive bank, read back, one-write activation,
   store) and the device corrects its own frames with it (IMU_RATE);
4. frames recorded after the push are corrected again offline by ``canical apply``,
   and the two are compared sample by sample.

It returns the figures (download time, time from push to corrected frames with the
new set, agreement with apply) for tests and benchmarks.
"""

from __future__ import annotations

import contextlib
import io
import math
import shutil
import tempfile
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from canical.bus.recording import Recording, open_recorder_bus, record
from canical.calibrate.plateaus import span_means
from canical.calibration.pipeline import CalibrateOptions, calibrate
from canical.device.can_network import open_network, sdo_client_filters, sdo_server_filters
from canical.device.emulated_imu import EmulatedImu, EmulatorConfig
from canical.device.sdo_download import ImuClient, PushResult, push_sets
from canical.errors import CanicalError
from canical.files.atomic_file import make_dirs, write_text_atomic
from canical.frames.imu_dictionary import AXES, sensor_id_for_serial
from canical.frames.imu_frames import ImuFrames, set_tag
from canical.sessions.csv_file import format_session, read_table
from canical.sets import coefficient_file
from canical.sets.coefficient_file import set_crc

TEMP_BIAS_DPS_PER_C = 0.03  # the undeclared effect of the demo's IMU
NOMINAL_COUNTS_PER_DPS = 400.0  # the datasheet's scale factor, for "before"
MIN_PLATEAU_ROWS = 10  # a settled run shorter than this is not a plateau of the live comparison


@dataclass(frozen=True)
class BusDemoOptions:
    interface: str = "virtual"
    channel: str = "canical-demo"
    node_id: int = 0x10
    serial: int = 4711
    axis: str = "z"
    sample_rate_hz: float = 100.0
    speed: float = 8.0
    table_rates: tuple[float, ...] = tuple(np.arange(-60.0, 60.1, 3.0).tolist())
    dwell_s: float = 2.0
    field_samples: int = 1500
    # The live comparison uses the first field_samples samples of this pass of the table
    # programme (0: the pass recorded for calibration), chosen by the device's sample index, so
    # that one seed compares the same frames whatever the timing. It must begin after the push:
    # 3 leaves ~20 s for recording, calibration and push at the defaults. None: the frames from
    # the first one corrected with the new set on (timing-dependent; for an external device).
    field_pass: int | None = 3
    emulate: bool = True  # False: a device is already running (``canical emulate``)
    timeout_s: float = 1.0


@dataclass
class BusDemoResult:
    session_csv: Path
    coefficients: Path
    set_id: int
    effects: list[str]
    held_out_rms_before_dps: float | None
    held_out_rms_after_dps: float | None
    push: PushResult
    push_to_correction_s: float
    field_samples: int
    live_rms_error_dps: float
    max_device_vs_apply_dps: float
    figures: dict[str, float] = field(default_factory=dict)


def default_bus() -> tuple[str, str]:
    """vcan0 when this machine has it, else python-can's in-process virtual bus."""
    import can

    try:
        can.Bus(interface="socketcan", channel="vcan0").shutdown()
    except Exception:  # no SocketCAN, no vcan0: python-can raises several types
        return "virtual", "canical-demo"
    return "socketcan", "vcan0"


def _emulator(options: BusDemoOptions, state: Path):
    from canical.sim.effects import TemperatureEffect
    from canical.sim.environment import temperature_steps
    from canical.sim.imu_stream import StreamConfig, TableMotion, default_gyros

    effect = TemperatureEffect(channel="temp_c", reference_c=25.0, bias_dps_per_c=TEMP_BIAS_DPS_PER_C)
    gyros = {a: g.__class__(**{**g.__dict__, "effects": (effect,)}) for a, g in default_gyros().items()}
    # The table sits in a thermal chamber stepping through temperatures in random order, so
    # temperature does not follow time since power-on and its effect can be told from a drift.
    chamber = temperature_steps(levels_c=(5.0, 20.0, 35.0, 50.0), period_s=12.0, time_constant_s=2.0)
    stream = StreamConfig(
        temperature=chamber,
        sample_rate_hz=options.sample_rate_hz,
        table=TableMotion(kind="steps", axis=options.axis, rates_dps=options.table_rates,
                          dwell_s=options.dwell_s),
        gyros=gyros,
    )
    filters = sdo_server_filters(options.node_id)
    network = open_network(options.interface, options.channel, can_filters=filters)
    config = EmulatorConfig(node_id=options.node_id, serial=options.serial, state_path=state, stream=stream,
                            speed=options.speed, correction=True)
    return network, EmulatedImu(config, network)


def run_bus_demo(out_dir: str | Path, options: BusDemoOptions | None = None,
                 say: Callable[[str], None] = print) -> BusDemoResult:
    """Run the loop; files go to ``out_dir``. See the module doc."""
    o = options or BusDemoOptions()
    out = Path(out_dir)
    make_dirs(out)
    # The device's flash and the files `canical apply` reads back are scratch, not results.
    scratch = Path(tempfile.mkdtemp(prefix="canical-demo-bus-"))
    frames = ImuFrames(o.node_id)
    device_net = device = thread = None
    if o.emulate:
        device_net, device = _emulator(o, scratch / "imu-state.json")  # a factory-fresh device
        thread = threading.Thread(target=device.run, name="emulated-imu", daemon=True)
    bus = open_recorder_bus(o.interface, o.channel, frames)
    tool_net = open_network(o.interface, o.channel, can_filters=sdo_client_filters(o.node_id))
    try:
        if device is not None and thread is not None:
            device.boot_up()
            thread.start()
        client = ImuClient(tool_net, o.node_id, o.timeout_s)
        serial = client.serial()
        sensor = sensor_id_for_serial(serial)
        where = f"{o.interface} {o.channel}"
        say(f"IMU node 0x{o.node_id:02x} on {where}: serial {serial} (sensor id {sensor}), "
            f"streaming raw frames at {o.sample_rate_hz:g} samples/s (x{o.speed:g} time)")

        # 1-2. Record one pass of the table programme, calibrate it.
        n_pass = _pass_samples(o)
        say(f"recording a turntable session from the bus: {len(o.table_rates)} plateaus, "
            f"{o.table_rates[0]:g}..{o.table_rates[-1]:g} deg/s, about {n_pass} samples")
        rec = record(bus, frames, samples=n_pass + 50)
        session = rec.session(o.axis, sensor)
        session_csv = out / "bus-session.csv"
        write_text_atomic(session_csv, format_session(session))
        say(f"  {len(session)} samples of axis {o.axis} ({rec.frames} frames) -> {session_csv}")
        result = calibrate(session, CalibrateOptions(), sensor_id=sensor, axis=o.axis)
        coeffs = out / f"imu-{o.axis}.yaml"
        coefficient_file.save(coeffs, result.coefficients)
        loop = result.report.closed_loop
        effects = [e.name for e in result.report.effects]
        before = loop.held_out_rms_before_dps if loop else None
        after = loop.held_out_rms_after_dps if loop else None
        found = ", ".join(effects) or "none"
        say(f"calibrated: {result.report.written_model()}; undeclared effect(s) found: {found}")
        if loop is not None:
            say(f"  held-out rms ({loop.blocks_label}, whole plateaus left out): rate model alone "
                f"{before:.4f}, written set {after:.4f} deg/s")
        set_id = set_crc(result.coefficients)
        say(f"  set 0x{set_id:08x} (its id covers its creation time: new every run) -> {coeffs}")

        # 3. Push while the device keeps streaming, and time until it corrects with the new set.
        new_tag = set_tag({a: (set_id if a == o.axis else 0) for a in AXES})
        t_push = time.monotonic()
        pushed = push_sets(client, {o.axis: (str(coeffs), result.coefficients)})
        assert isinstance(pushed, PushResult)
        say(f"pushed over SDO in {pushed.timings_s['total']:.3f} s "
            f"({pushed.bytes_written} bytes downloaded in {pushed.timings_s['download']:.3f} s); "
            f"device runs {pushed.status.describe()}")
        rule = NewSetRule.after(rec, new_tag, o.axis, pushed_at_s=time.monotonic())
        if rule.ambiguous:
            say(f"  the set before had the same 4-bit tag ({new_tag}): frames count as the new set's "
                "only once the push has returned")
        window = FieldWindow(rule, o.sample_rate_hz, n_pass, o.field_samples, o.field_pass)
        live = record(bus, frames, until=window)
        latency = float(live.array("received_s")[window.first_row()] - t_push)
        say(f"first frame corrected on the device with the new set {latency:.3f} s after the push began "
            f"(device sample {window.first_tagged})")

        # 4. The device's corrected rates against `canical apply` on the same frames.
        say(window.describe())
        inside = window.selects(live)
        tagged = inside & (live.array("device_tag") == new_tag)
        # A raw frame whose IMU_RATE was not matched (lost, or paired with another counter
        # value) has no device rate: compare only frames that have both.
        keep = tagged & np.isfinite(live.array(f"device_rate_{o.axis}"))
        if keep.sum() < o.field_samples:
            say(f"  of the window's {o.field_samples} samples: {int(inside.sum())} raw frames received, "
                f"{int(tagged.sum())} with the new set's tag, {int(keep.sum())} with a device rate")
        field_session = _field_session(live, keep, o.axis, sensor)
        applied = _apply_in(scratch, result.coefficients, format_session(field_session), out, say)
        write_text_atomic(out / "bus-field.csv", format_session(field_session))
        write_text_atomic(out / "bus-field-applied.csv", applied.read_text())
        apply_rate = read_table(applied, columns=["rate_dps"]).columns["rate_dps"]
        device_rate = live.array(f"device_rate_{o.axis}")[keep]
        diff = float(np.max(np.abs(apply_rate - device_rate)))
        ref = live.array("ref_dps")[keep]
        settled = live.array("settled")[keep] == 1
        nominal = (field_session.raw - result.coefficients.v0) / NOMINAL_COUNTS_PER_DPS
        nominal_rms = _plateau_rms(nominal, ref, settled)
        live_rms = _plateau_rms(device_rate, ref, settled)
        say(f"live: {int(keep.sum())} frames corrected on the device; error of plateau means against the "
            f"table: rms {nominal_rms:.3f} deg/s with the datasheet's linear scale "
            f"({NOMINAL_COUNTS_PER_DPS:g} counts per deg/s), {live_rms:.4f} deg/s corrected")
        say(f"  device output vs canical apply on the same frames: largest difference {diff:.4f} deg/s "
            f"(frame resolution 0.01)")
        return BusDemoResult(session_csv, coeffs, set_id, effects, before, after, pushed, latency,
                             int(keep.sum()), live_rms, diff)
    finally:
        if device is not None:
            device.stop_event.set()
        if thread is not None and thread.is_alive():
            thread.join(5)
        tool_net.disconnect()
        bus.shutdown()
        if device_net is not None:
            device_net.disconnect()
        shutil.rmtree(scratch, ignore_errors=True)


def _apply_in(scratch: Path, cset, field_csv: str, out: Path, say: Callable[[str], None]) -> Path:
    """``canical apply`` itself, run on the field frames in ``scratch``; returns the file it wrote.

    Its line is shown with the name the result gets in ``out``.
    """
    from canical.commands.cli import main as cli_main

    coeffs, data, applied = scratch / "set.yaml", scratch / "field.csv", scratch / "applied.csv"
    coeffs.write_text(coefficient_file.dumps(cset))
    data.write_text(field_csv)
    said = io.StringIO()
    with contextlib.redirect_stdout(said):
        status = cli_main(["apply", str(coeffs), str(data), "-o", str(applied)])
    if status != 0:
        raise CanicalError("canical apply failed on the recorded field data")
    say(said.getvalue().strip().replace(str(applied), str(out / "bus-field-applied.csv")))
    return applied


def _pass_samples(o: BusDemoOptions) -> int:
    from canical.sim.imu_stream import TableMotion, table_pass

    t, _, _ = table_pass(TableMotion(kind="steps", rates_dps=o.table_rates, dwell_s=o.dwell_s),
                         o.sample_rate_hz, 0.0)
    return len(t)


@dataclass(frozen=True)
class NewSetRule:
    """Which recorded frames the device corrected with the new set.

    IMU_RATE names the running sets by a 4-bit tag only, so one new set in 16 has the tag of
    the sets before it; a factory-fresh device's "no set" tag among them. A frame counts when
    it carries the new tag and a rate for the axis (not "uncalibrated"); where the set before
    also corrected the axis under the same tag (``ambiguous``), only frames received once the
    push had returned count: the device switched on activation, before the push's last step.
    """

    tag: int
    axis: str
    not_before_s: float  # time.monotonic() of receipt; -inf unless ambiguous

    @classmethod
    def after(cls, before: Recording, tag: int, axis: str, *, pushed_at_s: float) -> NewSetRule:
        """The rule for a push that returned at ``pushed_at_s``; ``before``: frames recorded before it."""
        tags = before.array("device_tag")
        rates = before.array(f"device_rate_{axis}")
        old = np.flatnonzero(np.isfinite(tags))
        same = bool(old.size) and tags[old[-1]] == tag and bool(np.isfinite(rates[old[-1]]))
        return cls(tag, axis, pushed_at_s if same else -math.inf)

    @property
    def ambiguous(self) -> bool:
        return math.isfinite(self.not_before_s)

    def carries(self, cols: dict[str, list[float]], i: int) -> bool:
        """Whether recorded sample ``i`` was corrected with the new set."""
        return (cols["device_tag"][i] == self.tag and math.isfinite(cols[f"device_rate_{self.axis}"][i])
                and cols["received_s"][i] >= self.not_before_s)


class FieldWindow:
    """Which recorded samples the live comparison uses: by the device's sample index, not arrival.

    The index is the frame's uptime (simulated time since power-on) times the sample rate, so
    a seed's stream gives the same samples in the window however late the push or slow the bus.
    Called with the recording so far, it says when the window is complete.
    """

    def __init__(
        self, rule: NewSetRule, fs_hz: float, pass_samples: int, n: int, pass_index: int | None
    ) -> None:
        self.rule, self.fs, self.pass_samples, self.n = rule, fs_hz, pass_samples, n
        self.wanted_pass = pass_index
        self.start: int | None = None  # first sample index of the window
        self.first_tagged: int | None = None  # sample index of the first frame with the new set
        self._first_row: int | None = None  # and its row in the recording
        self._seen = 0

    def _index(self, t: float) -> int | None:
        return round(t * self.fs) if math.isfinite(t) else None

    def __call__(self, rec: Recording) -> bool:
        cols = rec.columns
        # The newest sample may still get its corrected frame (device tag): look up to the one before.
        while self._seen < len(rec) - 1:
            i, self._seen = self._seen, self._seen + 1
            k = self._index(cols["time_s"][i])
            if k is None:
                continue
            if self.first_tagged is None and self.rule.carries(cols, i):
                self.first_tagged, self._first_row = k, i
                if self.wanted_pass is None:
                    self.start = k
                else:  # the wanted pass, or the first to begin after the set was running
                    after = -(-k // self.pass_samples)
                    self.start = max(self.wanted_pass, after) * self.pass_samples
            if self.start is not None and k >= self.start + self.n:
                return True
        return False

    def first_row(self) -> int:
        """The recording's row of the first frame corrected with the new set."""
        if self._first_row is None:
            raise CanicalError("the device never corrected with the new set")
        return self._first_row

    def _begun(self) -> int:
        """The window's first sample; a recording that stopped before it began compares nothing."""
        if self.start is None:
            raise CanicalError("the comparison window never began: no frame corrected with the new set")
        return self.start

    def selects(self, rec: Recording) -> np.ndarray:
        start = self._begun()
        k = np.rint(rec.array("time_s") * self.fs)
        inside: np.ndarray = (k >= start) & (k < start + self.n)
        return inside

    def describe(self) -> str:
        start = self._begun()
        where = f"samples {start}..{start + self.n - 1} of the device"
        if self.wanted_pass is None:
            return f"compared: {where}, from the first corrected with the new set"
        used = start // self.pass_samples
        if used == self.wanted_pass:
            return f"compared: {where} (table pass {used}, chosen by sample index: the same every run)"
        return (f"compared: {where} (table pass {used}: pass {self.wanted_pass} had begun before the "
                "new set ran, a slow machine; the figures below differ from the README's)")


def _field_session(rec: Recording, keep: np.ndarray, axis: str, sensor: str):
    from canical.sessions.session import Session

    return Session(
        time_s=rec.array("time_s")[keep],
        raw=rec.array(f"raw_{axis}")[keep],
        ref_dps=rec.array("ref_dps")[keep],
        aux={"temp_c": rec.array("temp_c")[keep], "supply_v": rec.array("supply_v")[keep]},
        meta={"sensor": sensor, "axis": axis},
    )


def _plateau_rms(rate: np.ndarray, ref: np.ndarray, settled: np.ndarray) -> float:
    """Rms over table plateaus of (mean rate − table rate): the calibration error, noise averaged out.

    A plateau here is a run of at least ``MIN_PLATEAU_ROWS`` rows the table flags settled at one
    rate: the few frames compared need no plateau finding, the table says where it stood still.
    """
    start, stop = _settled_runs(ref, settled)
    long_enough = stop - start >= MIN_PLATEAU_ROWS
    if not np.any(long_enough):
        return float("nan")
    start, stop = start[long_enough], stop[long_enough]
    errors = span_means(rate, start, stop) - ref[start]
    return float(np.sqrt(np.mean(np.square(errors))))


def _settled_runs(ref: np.ndarray, settled: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``[start, stop)`` of each run of settled rows at one table rate."""
    n = len(ref)
    boundary = np.ones(n + 1, dtype=bool)  # a run may begin (or the one before end) at each True
    boundary[1:n] = (ref[1:] != ref[:-1]) | (settled[1:] != settled[:-1])
    edges = np.flatnonzero(boundary)
    start, stop = edges[:-1], edges[1:]
    on = np.asarray(settled, dtype=bool)[start]
    return start[on], stop[on]
