"""The table grid through the bus flow: emulated IMU -> ``canical record`` -> ``canical calibrate``.

Each cell of :data:`support.trials.table_grid.GRID` is played by the emulated IMU
(:class:`canical.device.emulated_imu.EmulatedImu`, the device ``canical emulate`` runs) on
python-can's in-process virtual bus: ramped, ringing table motion, ``TABLE_REF`` frames
measured, held, late or on the table's own clock, IMU frames lost in bursts. ``canical
record`` writes one pass of the programme to a candump log and ``canical calibrate`` reads
it, exactly as from a real bus. The emulator runs as fast as the host allows (the samples'
times travel in ``IMU_AUX.Uptime``, not in arrival times), and the recorder is listening
before the first sample is sent, so a cell is deterministic: same seed, same frames.

The table's truth (its schedule) is known, so the rows plateau finding used are checked
against it as on the CSV grid; the held-out error is compared with the same sensor (same
seed, and the same noise at the same instants of each plateau,
:mod:`canical.sim.paired_noise`) on an ideal table through the same flow.
"""

from __future__ import annotations

import contextlib
import io
import json
import threading
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from canical.calibration.pipeline import CalibrateOptions, calibrate, find_plateaus
from canical.commands.cli import main
from canical.device.can_network import open_network, sdo_server_filters
from canical.device.emulated_imu import EmulatedImu, EmulatorConfig
from canical.sessions.canlog import read_canlog
from canical.sessions.session import Session
from canical.sim.imu_stream import StreamConfig, TableMotion, imu_blocks
from canical.sim.table_recording import TableBehaviour, schedule
from support.trials.table_grid import rows_on_rate_changes

DBC = Path(__file__).resolve().parents[3] / "canical" / "data" / "canical.dbc"
#: The bus version's programme, shorter than the CSV grid's (every frame goes through python-can
#: and a candump log): the same rates (-60..60 deg/s in 3 deg/s steps; sparser rates would make
#: the held-out error the model's interpolation, blind to the table), 8 s plateaus, 50 samples/s.
BUS_RATES = tuple(float(r) for r in np.linspace(-60.0, 60.0, 41))
BUS_DWELL_S = 8.0
BUS_FS_HZ = 50.0
UNBOUNDED_SPEED = 1e9  # simulated seconds per wall second: never wait for the clock
RECORD_READY_S = 30.0


@dataclass(frozen=True)
class BusCellResult:
    """One cell through the bus flow."""

    name: str
    seed: int
    scheduled: int
    found: int
    rates_ok: bool
    ramp_samples_used: int
    held_out_rms_dps: float
    frames: int  # raw frames recorded (one pass, lost bursts excluded)


class _ReadyWhenRecording(io.StringIO):
    """stdout of ``canical record``: says when its bus is open (its first line)."""

    def __init__(self) -> None:
        super().__init__()
        self.ready = threading.Event()

    def write(self, s: str) -> int:
        if s.startswith("record:"):
            self.ready.set()
        return super().write(s)


def _stream(behaviour: TableBehaviour, rates, dwell_s: float, fs_hz: float, seed: int) -> StreamConfig:
    return StreamConfig(sample_rate_hz=fs_hz, seed=seed,
                        table=TableMotion(rates_dps=tuple(rates), dwell_s=dwell_s, recording=behaviour))


def record_pass(behaviour: TableBehaviour, folder: Path, *, rates, dwell_s: float, fs_hz: float,
                seed: int, channel: str) -> tuple[Path, int]:
    """One pass of the programme, emulated and recorded from the virtual bus; (log, raw frames)."""
    stream = _stream(behaviour, rates, dwell_s, fs_hz, seed)
    first = next(imu_blocks(stream))  # the same pass the emulator will send
    n_frames = int(first.kept.sum()) if first.kept is not None else len(first)
    net = open_network("virtual", channel, can_filters=sdo_server_filters(0x10))
    device = EmulatedImu(EmulatorConfig(state_path=folder / "state.json", stream=stream,
                                        speed=UNBOUNDED_SPEED), net)
    out = _ReadyWhenRecording()

    def emulate() -> None:
        if out.ready.wait(RECORD_READY_S):
            device.run()

    thread = threading.Thread(target=emulate, name="emulated-imu", daemon=True)
    log = folder / "table.log"
    try:
        thread.start()
        with contextlib.redirect_stdout(out):
            status = main(["record", "-o", str(log), "--interface", "virtual", "--channel", channel,
                           "--dbc", str(DBC), "--frames", str(n_frames)])
    finally:
        device.stop_event.set()
        thread.join(30)
        net.disconnect()
    if status != 0:
        raise RuntimeError(f"canical record failed ({status}): {out.getvalue()}")
    return log, n_frames


def bus_cell(name: str, behaviour: TableBehaviour, folder: Path, *, rates=BUS_RATES,
             dwell_s: float = BUS_DWELL_S, fs_hz: float = BUS_FS_HZ, seed: int = 0) -> BusCellResult:
    """Emulate, record and calibrate one cell; check the used rows against the table's truth."""
    folder.mkdir(parents=True, exist_ok=True)
    channel = f"table-grid-bus-{seed}-{abs(hash(name)) % 1_000_000}"
    log, n_frames = record_pass(behaviour, folder, rates=rates, dwell_s=dwell_s, fs_hz=fs_hz, seed=seed,
                                channel=channel)
    report_path = folder / "report.json"
    with contextlib.redirect_stdout(io.StringIO()):
        status = main(["calibrate", str(log), "--dbc", str(DBC), "--input", "time_s=IMU_AUX.Uptime",
                       "--no-extend", "--sensor", "IMU-BUS", "-o", str(folder / "set.yaml"),
                       "--report", str(report_path)])
    if status != 0:
        raise RuntimeError(f"canical calibrate failed ({status}) on {log}")
    report = json.loads(report_path.read_text())
    # The rows calibrate used, as it found them in the same log.
    session = read_canlog(log, dbc=DBC, axis="z", inputs={"time_s": "IMU_AUX.Uptime"},
                          sensor="IMU-BUS").session
    p = find_plateaus(session, CalibrateOptions(extend=False))
    programme = np.concatenate([np.asarray(rates, dtype=float), [0.0]])  # a pass ends at rest
    sched = schedule(programme, dwell_s, behaviour, initial_dps=0.0)
    found_ok = p.count == sched.rates.size
    tol = np.maximum(0.05, 5 * p.rate_uncertainty())
    rates_ok = found_ok and bool(np.all(np.abs(p.rate_dps - sched.rates) <= tol))
    # Uptime is sent in milliseconds: a tick may read up to 1 ms off its true instant.
    ramp_rows = rows_on_rate_changes(p, sched, session.time_s, eps=1.5e-3)
    if p.count != report["plateaus"]:
        raise RuntimeError(f"{p.count} plateaus here, {report['plateaus']} in calibrate's report")
    return BusCellResult(name=name, seed=seed, scheduled=int(sched.rates.size), found=p.count,
                         rates_ok=rates_ok, ramp_samples_used=ramp_rows,
                         held_out_rms_dps=float(report["held_out"]["rms_dps"]), frames=n_frames)


def stream_session(behaviour: TableBehaviour, *, rates=BUS_RATES, dwell_s: float = BUS_DWELL_S,
                   fs_hz: float = BUS_FS_HZ, seed: int = 0) -> Session:
    """The pass the emulator sends, as a session recorded without the bus.

    The same samples, frame for frame: the kept rows, each with the reference the table sent
    for it (held at the latest of its own frames when they come at their own rate) and its
    settled flag. What the bus adds on top is only the frames' order, the DBC's scaling and
    the recorder's join; calibrating both and comparing is the bus's own cost.
    """
    block = next(imu_blocks(_stream(behaviour, rates, dwell_s, fs_hz, seed)))
    kept = block.kept if block.kept is not None else np.ones(len(block), dtype=bool)
    ref = block.ref_dps if block.ref_dps is not None else block.table_rate_dps
    return Session(time_s=block.time_s[kept], raw=block.raw["z"][kept], ref_dps=ref[kept],
                   aux={"Temperature": block.temp_c[kept], "SupplyVoltage": block.supply_v[kept]},
                   meta={"sensor": "IMU-NO-BUS", "axis": "z"}, settled=block.settled[kept])


def stream_held_out_rms(behaviour: TableBehaviour, *, seed: int = 0, **kw) -> float:
    """Held-out rms of :func:`stream_session` calibrated as ``canical calibrate`` does."""
    result = calibrate(stream_session(behaviour, seed=seed, **kw), CalibrateOptions(extend=False),
                       sensor_id="IMU-NO-BUS", axis="z")
    return float(result.report.held_out.rms_dps)


def pooled_bus_ratio(results: list[BusCellResult], ideal: dict[int, BusCellResult]) -> float:
    """Held-out rms over the cells' seeds relative to the same seeds' ideal cells (as on the CSV grid)."""
    cell = np.sqrt(np.mean([r.held_out_rms_dps**2 for r in results]))
    base = np.sqrt(np.mean([ideal[r.seed].held_out_rms_dps**2 for r in results]))
    return float(cell / base)
