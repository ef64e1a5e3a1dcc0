"""``canical simulate``: the sessions, triads and drives the docs use, for a user without hardware.

Why: every feature should be tried before the IMU arrives, on the layout of the user's own DBC.
``session`` is a turntable session (−60…60 deg/s in 3 deg/s steps; a temperature cycling and a
bias that follows it, for the closed loop to find), ``drive`` a drive with stops, turns, creep,
power cycles and a warming cabin (for ``apply --track-bias``), ``triad`` one session per axis of
a three-axis IMU with cross-axis coupling (for ``calibrate x.csv y.csv z.csv``). The same
``--seed`` is the same sensor: a set calibrated from ``simulate session`` corrects
``simulate drive``; ``fleet`` writes the field logs of many vehicles
(:mod:`.simulate_fleet`). A CSV is written in the format ``calibrate`` and ``apply`` read; a CAN log
(``-o`` ending in a log suffix, with ``--config``) holds the frames the configuration's IMU would
send: the raw message with the axis's signal, each mapped channel in its message, and for a
session canical's ``TABLE_REF`` (the rate table on the bus). With ``--table-file`` the table is
not on the bus: it logs its rate to a file of its own, on its own clock, beside each log (what
``calibrate --reference`` reads). Truth (the sensor's model) is printed.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from canical.commands import COMMANDS
from canical.errors import CanicalError

if TYPE_CHECKING:
    import numpy as np
    from cantools.database.can import Signal

    from canical.bus.daemon_config import AxisConfig, DaemonConfig
    from canical.files.output_plan import OutputPlan
    from canical.sim.bus_log import LogPlan, SignalTrack
    from canical.sim.gyro import GyroModel

KINDS = ("session", "drive", "triad", "fleet")
#: The column names a simulated drive or session writes, as the docs name them.
TEMP, TIME, SPEED = "temp_c", "time_s", "speed_mps"
#: A drive's clock since it began (power-off gaps included): its log's timestamps, not a column
#: (``time_s`` is time since power-on, starting again at each power cycle, as a recorded drive's).
CLOCK = "clock_s"


def register(sub) -> None:
    p = sub.add_parser("simulate", help=COMMANDS["simulate"], description=__doc__.split("\n\n")[0])
    p.add_argument("kind", choices=KINDS, help="what to simulate")
    p.add_argument("-o", "--output", required=True,
                   help="CSV (a session or drive), a CAN log (.log, .asc, .blf; with --config), or for "
                        "a triad a folder (x.csv, y.csv, z.csv); for a fleet a new or empty folder")
    p.add_argument("--config", help="daemon configuration: a log in its DBC's layout (raw message, "
                                    "inputs); its first calibrated axis is the one simulated")
    p.add_argument("--seed", type=int, default=0, help="the sensor and its noise [0]")
    p.add_argument("--temp-slope", type=float, default=0.01, metavar="DPS_PER_C",
                   help="the sensor's bias per °C, which no declared model has [0.01]")
    p.add_argument("--vehicles", type=int, metavar="N",
                   help="fleet: how many vehicles (each one sensor; -o is a folder: one folder of field-log "
                        "segments per vehicle and truth.csv)")
    p.add_argument("--days", type=int, metavar="D", help="fleet: how many days of driving")
    p.add_argument("--drives", type=int, metavar="K",
                   help="fleet: also K raw drives per vehicle (drives/VEHICLE/drive-NNN.csv, its sensor's "
                        "truth) and each sensor's baseline set (sets/SENSOR.yaml), for fleet replay; "
                        "needs --drive-set")
    p.add_argument("--drive-set", metavar="SET",
                   help="fleet --drives: the set (segmented, no effect terms) every sensor's baseline "
                        "set copies under its id; the raw drives are its rate model inverted")
    p.add_argument("--table-file", action="store_true",
                   help="the table logs its rate to its own file, on its own clock (5000.25 s off, "
                        "75 ppm slow), not on the bus: each log (with --config) gets no TABLE_REF, and "
                        "STEM-table.csv beside it is the table's file, for calibrate --reference")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from canical.sessions.canlog_format import is_canlog

    out = Path(args.output)
    if args.kind == "fleet":
        from canical.commands.simulate_fleet import run_fleet

        if args.config or args.table_file:
            raise CanicalError("simulate fleet: --config and --table-file are for a session, drive or triad")
        return run_fleet(args)
    if args.vehicles is not None or args.days is not None or args.drives is not None:
        raise CanicalError("--vehicles, --days and --drives are for simulate fleet")
    check_table_file(args)
    if args.kind == "triad":
        from canical.commands.simulate_triad import run_triad

        return run_triad(args, out)
    as_log = is_canlog(out) or out.suffix in (".log", ".asc", ".blf")
    if as_log and not args.config:
        raise CanicalError(f"{out}: a CAN log is written in a DBC's layout: give --config (the daemon "
                           "configuration naming the DBC, raw signal and inputs), or -o a .csv")
    if args.table_file and not as_log:
        raise CanicalError(f"--table-file: {out} is a CSV, which carries the table's rate (ref_dps): "
                           "-o a CAN log (.log, .asc, .blf) with --config")
    config = _config(args.config) if args.config else None
    gyro = _gyro(config, args.temp_slope)
    columns = _session(gyro, args.seed) if args.kind == "session" else _drive(gyro, args.seed)
    if config is not None and as_log:
        _write_session_log(out, config, columns, args)
    else:
        _write_csv(out, columns)
    n, seconds = len(columns["time_s"]), float(columns.get(CLOCK, columns["time_s"])[-1])
    print(f"simulate: {args.kind} of {n} samples ({seconds:.0f} s) -> {out}")
    print(f"  sensor: V0 {gyro.bias_counts:g}, {gyro.sensitivity:g} per deg/s, bias "
          f"{args.temp_slope:g} deg/s/°C from 25 °C; seed {args.seed}")
    if args.table_file:
        print(table_line([table_path(out)]))
    return 0


def check_table_file(args: argparse.Namespace) -> None:
    """``--table-file`` writes a table's file beside CAN logs: a drive has no table, and a CSV
    (or a triad of CSVs) carries the table's rate in its own column."""
    if not args.table_file:
        return
    if args.kind == "drive":
        raise CanicalError("--table-file: a drive has no rate table; it is for a session or a triad")
    if not args.config:
        raise CanicalError("--table-file: the table's file goes beside a CAN log of the sensor's frames: "
                           "give --config (the daemon configuration naming the DBC and raw signal)")


def table_path(log: Path) -> Path:
    """The table's own file beside a log: ``imu.log`` -> ``imu-table.csv``."""
    return log.with_name(f"{log.stem}-table.csv")


def table_line(paths: list[Path]) -> str:
    """Where the table's files went and how its clock is off (what --reference will find)."""
    from canical.sim.table_file import TableClock

    clock = TableClock()
    return (f"  table: not on the bus; its own file{'s' if len(paths) > 1 else ''} "
            f"{', '.join(p.name for p in paths)} beside the log, on its own clock ({clock.offset_s:g} s "
            f"off, {clock.drift_ppm:+g} ppm): give it to calibrate --reference")


def _config(path: str) -> DaemonConfig:
    from canical.bus.daemon_config import load_config

    config = load_config(path)
    if not config.axes:
        raise CanicalError(f"{path}: no axis configured")
    return config


def _gyro(config: DaemonConfig | None, temp_slope: float) -> GyroModel:
    """The simulated sensor: counts on canical's own frames; on a signal in a physical unit
    (a vendor's deg/s), the same sensor in that unit at that signal's resolution."""
    from canical.sim.effects import TemperatureEffect
    from canical.sim.gyro import GyroModel

    gyro = GyroModel(effects=(TemperatureEffect(bias_dps_per_c=temp_slope),))
    if config is None:
        return gyro
    return in_signal_units(gyro, raw_signal(config, _axis(config)), per_dps=1.0, bias=0.3)


def in_signal_units(gyro: GyroModel, signal: Signal, *, per_dps: float, bias: float) -> GyroModel:
    """The sensor as a signal in a physical unit carries it (``per_dps`` of that unit per deg/s,
    rounded to the signal's resolution, clipped at its range); unchanged on a signal in counts."""
    if signal.unit in ("", "counts", None):
        return gyro
    rail = float(signal.maximum) if signal.maximum is not None else 1e9
    return replace(gyro, sensitivity=per_dps, bias_counts=bias, lsb=float(signal.conversion.scale),
                   rail_counts=rail)


def raw_signal(config: DaemonConfig, axis: AxisConfig) -> Signal:
    """The axis's raw signal as its DBC defines it: its unit, resolution and range."""
    from canical.frames.codec import load_dbc

    db = load_dbc(config.dbc_path)
    message = db.get_message_by_name(axis.message or config.raw_message)
    return message.get_signal_by_name(str(axis.raw_signal))


def _axis(config: DaemonConfig) -> AxisConfig:
    """The axis a simulated log carries: the first with a set, else the last named one."""
    named = [a for a in config.axes if a.present]
    return next((a for a in named if a.coefficients is not None), named[-1])


def _session(gyro: GyroModel, seed: int) -> dict[str, np.ndarray]:
    from canical.sim.environment import temperature_cycle
    from canical.sim.sessions import paper_session

    session = paper_session(gyro, seed=seed, sweeps=2, aux={TEMP: temperature_cycle()})  # up and down:
    # each rate visited at two temperatures, so the temperature is not a function of the rate
    return {"time_s": session.time_s, "ref_dps": session.reference(), "raw": session.raw,
            TEMP: session.aux[TEMP]}


def _drive(gyro: GyroModel, seed: int) -> dict[str, np.ndarray]:
    """The drive's rate (true rate, turn-on bias, vibration, noise) through the sensor's curve."""
    import numpy as np

    from canical.sim.drive import simulate_drive

    drive = simulate_drive(seed)
    quiet = replace(gyro, effects=())  # the drive's own bias model holds the temperature's
    raw = quiet.output(drive.time_s, drive.rate_dps, fs_hz=drive.rate_hz,
                       noise_dps=np.zeros(drive.time_s.size))
    return {"time_s": drive.time_s, "raw": raw, TEMP: drive.temp_c, SPEED: drive.speed_mps,
            CLOCK: drive.clock_s}


def _write_csv(out: Path, columns: dict[str, np.ndarray]) -> None:
    import io

    import numpy as np

    from canical.files.atomic_file import write_text_atomic

    buf = io.StringIO()
    buf.write("# sensor: SIM-0001\n# axis: z\n")
    written = {k: v for k, v in columns.items() if k != CLOCK}
    buf.write(",".join(written) + "\n")
    np.savetxt(buf, np.column_stack(list(written.values())), delimiter=",", fmt="%.9g")
    write_text_atomic(out, buf.getvalue())


def _write_session_log(out: Path, config: DaemonConfig, columns: dict[str, np.ndarray],
                       args: argparse.Namespace) -> None:
    """A session's or drive's log; a session's table on the bus, or in its own file beside it."""
    from canical.files.output_plan import output_plan

    table_file = table_path(out) if args.table_file else None
    with output_plan(out, table_file) as files:
        on_bus = args.kind == "session" and table_file is None
        write_plan(files, out, log_plan(config, columns, table_on_bus=on_bus))
        if table_file is not None:
            write_table_file(table_file, columns["time_s"], columns["ref_dps"], args.seed)


def write_table_file(path: Path, time_s: np.ndarray, ref_dps: np.ndarray, seed: int) -> None:
    from canical.files.atomic_file import write_text_atomic
    from canical.sim.table_file import TableClock, table_csv, table_rows

    write_text_atomic(path, table_csv(table_rows(time_s, ref_dps, TableClock(), seed)))


def sent_id(config: DaemonConfig, message) -> int:
    """The id a message goes out with: a J1939 group from the IMU's configured source address."""
    from canical.frames.frame_match import frame_match

    return frame_match(message, config.j1939_source).usual_id


def log_plan(config: DaemonConfig, columns: dict[str, np.ndarray], *, table_on_bus: bool) -> LogPlan:
    """The frames of a one-axis session or drive: the raw message, the mapped channels, and
    (``table_on_bus``) canical's ``TABLE_REF`` with the table's rate, axis and settled flag."""
    import numpy as np

    from canical.frames.codec import load_dbc
    from canical.sim import bus_log

    db = load_dbc(config.dbc_path)
    axis = _axis(config)
    raw_message = db.get_message_by_name(axis.message or config.raw_message)
    t = columns.get(CLOCK, columns["time_s"])
    assert axis.raw_signal is not None
    raw = bus_log.SignalTrack(raw_message, axis.raw_signal,
                              bus_log.physical(raw_message, axis.raw_signal, columns["raw"]),
                              sent_id(config, raw_message))
    table: tuple[bus_log.SignalTrack, ...] = ()
    if table_on_bus:
        steady = np.r_[0.0, (np.diff(columns["ref_dps"]) == 0).astype(float)]  # the table's own flag
        table = bus_log.table_tracks(db, columns["ref_dps"], bus_log.AXES.index(axis.axis), steady)
    return bus_log.LogPlan(t, (raw,), channel_tracks(config, db, columns, t, raw_message.name), table)


def channel_tracks(config: DaemonConfig, db, columns: dict[str, np.ndarray], t: np.ndarray,
                   raw_message: str) -> tuple[SignalTrack, ...]:
    """Each input the configuration maps and the simulation has (a speed from ``speed_mps``), in
    its own message at the channels' rate; an input in the raw message is not a frame of its own."""
    from canical.sim import bus_log

    channels = []
    for name, source in config.inputs.items():
        column = columns.get(name, columns.get(SPEED) if name.startswith("speed") else None)
        if column is None or source.message == raw_message:
            continue
        message = db.get_message_by_name(source.message)
        values = bus_log.decimate(column, t)
        channels.append(bus_log.SignalTrack(message, source.signal,
                                            bus_log.physical(message, source.signal, values),
                                            sent_id(config, message)))
    return tuple(channels)


def write_plan(files: OutputPlan, out: Path, plan: LogPlan) -> None:
    """The plan's frames as a CAN log (its format from the suffix), staged until the command ends."""
    import can

    from canical.sim import bus_log

    with can.Logger(str(files.temp_path(out))) as logger:
        for frame in bus_log.messages(plan):
            logger.on_message_received(frame)
