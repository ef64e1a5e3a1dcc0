"""``canical simulate``: the sessions, triads and drives the docs use, for a user without hardware.

Why: every feature should be tried before the IMU arrives, on the layout of the user's own DBC.
``session`` is a turntable session (−60…60 deg/s in 3 deg/s steps; a temperature cycling and a
bias that follows it, for the closed loop to find), ``drive`` a drive with stops, turns, creep,
power cycles and a warming cabin (for ``apply --track-bias``), ``triad`` one session per axis of
a three-axis IMU with cross-axis coupling (for ``calibrate x.csv y.csv z.csv``). The same
``--seed`` is the same sensor: a set calibrated from ``simulate session`` corrects
``simulate drive``. A CSV is written in the format ``calibrate`` and ``apply`` read; a CAN log
(``-o`` ending in a log suffix, with ``--config``) holds the frames the configuration's IMU would
send: the raw message with the axis's signal, each mapped channel in its message, and for a
session canical's ``TABLE_REF`` (the rate table on the bus). Truth (the sensor's model) is printed.
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

    from canical.bus.daemon_config import DaemonConfig
    from canical.sim.gyro import GyroModel

KINDS = ("session", "drive", "triad")
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
                        "a triad a folder (x.csv, y.csv, z.csv)")
    p.add_argument("--config", help="daemon configuration: a log in its DBC's layout (raw message, "
                                    "inputs); its first calibrated axis is the one simulated")
    p.add_argument("--seed", type=int, default=0, help="the sensor and its noise [0]")
    p.add_argument("--temp-slope", type=float, default=0.01, metavar="DPS_PER_C",
                   help="the sensor's bias per °C, which no declared model has [0.01]")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from canical.sessions.canlog_format import is_canlog

    out = Path(args.output)
    if args.kind == "triad":
        return _triad(args, out)
    as_log = is_canlog(out) or out.suffix in (".log", ".asc", ".blf")
    if as_log and not args.config:
        raise CanicalError(f"{out}: a CAN log is written in a DBC's layout: give --config (the daemon "
                           "configuration naming the DBC, raw signal and inputs), or -o a .csv")
    config = _config(args.config) if args.config else None
    gyro = _gyro(config, args.temp_slope)
    columns = _session(gyro, args.seed) if args.kind == "session" else _drive(gyro, args.seed)
    if config is not None and as_log:
        _write_log(out, config, columns, args.kind)
    else:
        _write_csv(out, columns)
    n, seconds = len(columns["time_s"]), float(columns.get(CLOCK, columns["time_s"])[-1])
    print(f"simulate: {args.kind} of {n} samples ({seconds:.0f} s) -> {out}")
    print(f"  sensor: V0 {gyro.bias_counts:g}, {gyro.sensitivity:g} per deg/s, bias "
          f"{args.temp_slope:g} deg/s/°C from 25 °C; seed {args.seed}")
    return 0


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
    signal = _raw_signal(config)
    if signal.unit in ("", "counts", None):
        return gyro
    rail = float(signal.maximum) if signal.maximum is not None else 1e9
    return replace(gyro, sensitivity=1.0, bias_counts=0.3, lsb=float(signal.conversion.scale),
                   rail_counts=rail)


def _raw_signal(config: DaemonConfig):
    from canical.frames.codec import load_dbc

    axis = _axis(config)
    db = load_dbc(config.dbc_path)
    message = db.get_message_by_name(axis.message or config.raw_message)
    return message.get_signal_by_name(axis.raw_signal)


def _axis(config: DaemonConfig):
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


def _write_log(out: Path, config: DaemonConfig, columns: dict[str, np.ndarray], kind: str) -> None:
    import can
    import numpy as np

    from canical.files.output_plan import output_plan
    from canical.frames.codec import load_dbc
    from canical.frames.frame_match import frame_match
    from canical.sim import bus_log

    db = load_dbc(config.dbc_path)
    axis = _axis(config)
    raw_message = db.get_message_by_name(axis.message or config.raw_message)
    t = columns.get(CLOCK, columns["time_s"])
    def sent_id(message) -> int:  # a J1939 group from the IMU's configured source address
        return frame_match(message, config.j1939_source).usual_id

    assert axis.raw_signal is not None
    raw = bus_log.SignalTrack(raw_message, axis.raw_signal,
                              bus_log.physical(raw_message, axis.raw_signal, columns["raw"]),
                              sent_id(raw_message))
    channels = []
    for name, source in config.inputs.items():
        column = columns.get(name, columns[SPEED] if name.startswith("speed") else None)
        if column is None or source.message == raw_message.name:
            continue
        message = db.get_message_by_name(source.message)
        values = bus_log.decimate(column, t)
        channels.append(bus_log.SignalTrack(message, source.signal,
                                            bus_log.physical(message, source.signal, values),
                                            sent_id(message)))
    table: tuple[bus_log.SignalTrack, ...] = ()
    if kind == "session":
        ref = db.get_message_by_name(bus_log.TABLE_REF)
        axis_code = np.full(t.size, float(bus_log.AXES.index(axis.axis)))
        steady = np.r_[0.0, (np.diff(columns["ref_dps"]) == 0).astype(float)]  # the table's own flag
        table = (bus_log.SignalTrack(ref, "TableRate", columns["ref_dps"]),
                 bus_log.SignalTrack(ref, "TableAxis", axis_code),
                 bus_log.SignalTrack(ref, "TableSettled", steady))
    plan = bus_log.LogPlan(t, (raw,), tuple(channels), table)
    with output_plan(out) as files, can.Logger(str(files.temp_path(out))) as logger:
        for frame in bus_log.messages(plan):
            logger.on_message_received(frame)


def _triad(args: argparse.Namespace, out: Path) -> int:
    from canical.files.atomic_file import make_dirs, write_text_atomic
    from canical.files.output_plan import output_plan
    from canical.sessions.triad_session import format_triad_session
    from canical.sim.triad import axis_session, random_triad

    triad = random_triad(args.seed)
    with output_plan(dirs=[out]):
        make_dirs(out)
        for axis in ("x", "y", "z"):
            session = axis_session(triad, axis, seed=args.seed)
            write_text_atomic(out / f"{axis}.csv", format_triad_session(session))
    print(f"simulate: triad of three sessions (table about x, y, z) -> {out}/x.csv, y.csv, z.csv")
    print(f"  coupling (true): {[[round(v, 4) for v in row] for row in triad.coupling.tolist()]}")
    return 0
