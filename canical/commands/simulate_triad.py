"""``canical simulate triad``: one session per axis of a three-axis IMU, as CSVs or CAN logs.

Why: a user without hardware should try ``calibrate x y z -o imu.yaml`` on the data their own
IMU will give: CSVs (``x.csv``...) without ``--config``; with it, CAN logs in the layout of the
user's DBC (``x.log``...: the raw message with every axis's signal, and canical's ``TABLE_REF``
naming the turning axis), or with ``--table-file`` logs of the IMU's frames alone and the table's
own file beside each (``x-table.csv``..., on its own clock), for ``calibrate --reference``.
"""

from __future__ import annotations

import argparse
from dataclasses import replace
from pathlib import Path
from typing import TYPE_CHECKING

from canical.commands.simulate import (
    TEMP,
    channel_tracks,
    in_signal_units,
    raw_signal,
    sent_id,
    table_line,
    table_path,
    write_plan,
)
from canical.errors import CanicalError

if TYPE_CHECKING:
    from canical.bus.daemon_config import AxisConfig, DaemonConfig
    from canical.files.output_plan import OutputPlan
    from canical.sessions.triad_session import TriadSession
    from canical.sim.triad import TriadModel

AXES = ("x", "y", "z")
#: The simulated triad's nominal sensitivity, counts per deg/s (canical.sim.triad.random_gyro):
#: on a vendor's deg/s signal each axis keeps its own relative scale error and bias about it.
NOMINAL_COUNTS_PER_DPS = 100.0
#: The triad is simulated without a temperature effect, in a chamber held here (a configured
#: temp_c input is sent at it, so that the log has every channel the configuration reads).
CHAMBER_C = 25.0


def run_triad(args: argparse.Namespace, out: Path) -> int:
    from canical.bus.daemon_config import load_config
    from canical.files.atomic_file import make_dirs, write_text_atomic
    from canical.files.output_plan import output_plan
    from canical.sessions.triad_session import format_triad_session
    from canical.sim.triad import axis_session, random_triad

    config = load_config(args.config) if args.config else None
    triad = random_triad(args.seed)
    if config is not None:
        triad = triad_in_config_units(triad, config, args.config)
    with output_plan(dirs=[out]) as files:
        make_dirs(out)
        for axis in AXES:
            session = axis_session(triad, axis, seed=args.seed)
            if config is None:
                write_text_atomic(out / f"{axis}.csv", format_triad_session(session))
            else:
                write_axis_log(files, out / f"{axis}.log", config, session, args)
    suffix = ".csv" if config is None else ".log"
    print(f"simulate: triad of three sessions (table about x, y, z) -> {out}/x{suffix}, y{suffix}, z{suffix}")
    if args.table_file:
        print(table_line([table_path(out / f"{a}.log") for a in AXES]))
    print(f"  coupling (true): {[[round(v, 4) for v in row] for row in triad.coupling.tolist()]}")
    return 0


def configured_axes(config: DaemonConfig, name: str) -> list[AxisConfig]:
    """The configuration's x, y and z, all in one message: what a simulated triad log carries."""
    named = {a.axis: a for a in config.axes if a.present and a.raw_signal is not None}
    missing = [a for a in AXES if a not in named]
    if missing:
        raise CanicalError(f"{name}: a triad needs axes x, y and z named (axes.AXIS.raw); "
                           f"{', '.join(missing)} missing")
    axes = [named[a] for a in AXES]
    if len({a.message or config.raw_message for a in axes}) > 1:
        raise CanicalError(f"{name}: simulate triad writes the three axes in one message; these are in "
                           "several (name three signals of one message under axes)")
    return axes


def triad_in_config_units(triad: TriadModel, config: DaemonConfig, name: str) -> TriadModel:
    """Each axis as its configured signal carries it (a vendor's deg/s at the signal's resolution)."""
    axes = configured_axes(config, name)
    x, y, z = (in_signal_units(g, raw_signal(config, a), per_dps=g.sensitivity / NOMINAL_COUNTS_PER_DPS,
                               bias=g.bias_counts / NOMINAL_COUNTS_PER_DPS)
               for g, a in zip(triad.gyros, axes, strict=True))
    return replace(triad, gyros=(x, y, z))


def write_axis_log(files: OutputPlan, log: Path, config: DaemonConfig, session: TriadSession,
                   args: argparse.Namespace) -> None:
    """One axis's session as the bus carries it; its table on the bus, or in its own file."""
    import numpy as np

    from canical.commands.simulate import write_table_file
    from canical.frames.codec import load_dbc
    from canical.sim import bus_log

    db = load_dbc(config.dbc_path)
    axes = configured_axes(config, str(args.config))
    message = db.get_message_by_name(axes[0].message or config.raw_message)
    signals = [(str(a.raw_signal), column) for a, column in zip(axes, session.raw.T, strict=True)]
    raw = tuple(bus_log.SignalTrack(message, name, bus_log.physical(message, name, column),
                                    sent_id(config, message)) for name, column in signals)
    assert session.table_axis is not None
    index, sign = session.table_axis.index, session.table_axis.sign
    ref = sign * session.rate_dps[:, index]  # the table's rate about its own axis
    table: tuple[bus_log.SignalTrack, ...] = ()
    if not args.table_file:
        steady = np.r_[0.0, (np.diff(ref) == 0).astype(float)]
        table = bus_log.table_tracks(db, ref, index, steady, inverted=sign < 0)
    columns = {TEMP: np.full(session.time_s.size, CHAMBER_C), "time_s": session.time_s}
    channels = channel_tracks(config, db, columns, session.time_s, message.name)
    write_plan(files, log, bus_log.LogPlan(session.time_s, raw, channels, table))
    if args.table_file:
        write_table_file(table_path(log), session.time_s, ref, args.seed * 3 + index)
