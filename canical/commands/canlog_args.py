"""Options shared by commands that read CAN logs: which DBC, and where each channel comes from.

``--config`` takes all of it from a daemon configuration, so that a log is read with exactly
the mapping the daemon uses on the vehicle; ``--dbc`` and ``--input NAME=MESSAGE.Signal``
give it by hand (and override the configuration's).
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from canical.errors import CanicalError
from canical.sessions.canlog_format import CANLOG_FORMATS

if TYPE_CHECKING:
    from canical.frames.dbc_files import DbcSet
    from canical.frames.frame_match import J1939Source


@dataclass(frozen=True)
class CanlogSource:
    dbc: DbcSet  # the DBC files (canical's own frames are loaded beside them)
    inputs: dict[str, str]  # channel name -> MESSAGE.Signal
    raw_message: str
    raw_signals: dict[str, str]  # axis -> raw signal
    sensor: str | None
    from_config: bool
    j1939_source: J1939Source = None  # J1939 messages: the DBC's source address (None), a given one, or any
    raw_named: bool = False  # --input raw=MESSAGE.Signal named the gyro signal on the command line

    def axis_inputs(self, axis: str, names: list[str] | tuple[str, ...]) -> dict[str, str]:
        """The inputs ``names`` and, for an axis in another message than the raw frame, its held raw
        signal ("@x", as ``raw_signals`` names it): what reading the axis from a log needs."""
        held = self.raw_signals.get(axis)
        wanted = [*names, *([held] if held is not None and held in self.inputs else [])]
        return {n: self.inputs[n] for n in dict.fromkeys(wanted)}


def add_canlog_arguments(parser: argparse.ArgumentParser) -> None:
    group = parser.add_argument_group(f"CAN logs ({CANLOG_FORMATS})")
    group.add_argument("--dbc", action="append", metavar="DBC",
                       help="DBC that describes the log's frames (repeatable: several files)")
    group.add_argument("--config", help="daemon configuration: its DBC, frames and input mapping")
    group.add_argument("--input", action="append", dest="inputs", metavar="NAME=MESSAGE.Signal",
                       help="a channel from a signal, held at its latest value (repeatable); "
                            "raw=MESSAGE.Signal names the gyro signal of a one-axis log")
    group.add_argument("--j1939-message", action="append", dest="j1939_messages", metavar="MESSAGE|all",
                       help="a message that is a J1939 parameter group though the DBC does not say so "
                            "(no VFrameFormat/ProtocolType attribute; repeatable; all: every extended-id "
                            "message) [the configuration's j1939.messages]")
    group.add_argument("--j1939-source", metavar="ADDR|any",
                       help="J1939 messages are matched by parameter group; this source address, or any "
                            "[the DBC's, or the configuration's j1939.source_address]")


#: ``--input raw=MESSAGE.Signal``: the gyro signal of a one-axis CAN log (not a channel).
RAW_INPUT = "raw"
AXIS_NAMES = ("x", "y", "z")


def canlog_source(args: argparse.Namespace, log_file: str) -> CanlogSource:
    """Resolve the options; a log without a DBC is one actionable error line."""
    from canical.bus.daemon_config import load_config  # cantools: not for every command's --help
    from canical.frames.dbc_files import DbcSet
    from canical.frames.frame_match import parse_j1939_source
    from canical.sessions.canlog import parse_signal_map
    from canical.sessions.canlog_format import DEFAULT_RAW_MESSAGE

    inputs: dict[str, str] = {}
    raw_message = DEFAULT_RAW_MESSAGE
    raw_signals: dict[str, str] = {}
    sensor = None
    dbc = None
    j1939: J1939Source = None
    if args.config:
        config = load_config(args.config)
        dbc = config.dbc_path
        inputs = {name: f"{s.message}.{s.signal}" for name, s in config.inputs.items()}
        raw_message = config.raw_message
        # An axis in another message than the raw frame: held among the inputs ("@x"), as the daemon does.
        raw_signals = {a.axis: a.held or a.raw_signal for a in config.axes if a.raw_signal is not None}
        sensor = config.sensor
        j1939 = config.j1939_source
    if getattr(args, "j1939_source", None) is not None:
        try:
            j1939 = parse_j1939_source(args.j1939_source, "--j1939-source")
        except ValueError as exc:
            raise CanicalError(str(exc)) from None
    if args.dbc:
        dbc = DbcSet(Path(p) for p in args.dbc)
    if dbc is None:
        raise CanicalError(f"{log_file}: reading a CAN log needs --dbc or --config")
    if getattr(args, "j1939_messages", None):
        dbc = DbcSet(dbc, j1939=[*dbc.j1939, *args.j1939_messages])
    inputs.update(parse_signal_map(args.inputs))
    named = inputs.pop(RAW_INPUT, None)
    if named is not None:  # one axis's gyro signal, for every command that reads one axis
        raw_message, _, signal = named.partition(".")
        raw_signals = dict.fromkeys(AXIS_NAMES, signal)
    return CanlogSource(dbc, inputs, raw_message, raw_signals, sensor, bool(args.config), j1939,
                        raw_named=named is not None)


def refuse_raw_for_a_triad(source: CanlogSource, command: str) -> None:
    """``--input raw=`` names one signal; three axes need three (the configuration's ``axes``)."""
    if source.raw_named:
        raise CanicalError(f"{command}: --input raw=MESSAGE.Signal names one axis's gyro signal; three "
                           "axes are read with --config, whose axes name each axis's raw signal")
