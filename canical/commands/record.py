"""``canical record``: record a session from the bus into a CAN log that ``calibrate`` reads.

python-can's ``Logger`` writes the format the output's suffix names (candump ``.log``, ``.asc``,
``.blf``, ``.trc``, ``.csv``, ``.db``, ``.mf4``, each also ``.gz``): every one reads back.
A log of the frames themselves (not decoded samples) is the lossless record: it is read
back with the DBC by the same rules as the daemon, and can be re-read with another mapping.
Only the frames a session needs pass the kernel's receive filters: the IMU's (the raw frame
and the frames carrying inputs) and the rate table's reference. The file appears, complete,
when recording ends (after ``--duration``, ``--frames`` raw frames, or Ctrl-C).
"""

from __future__ import annotations

import argparse
import errno
import signal
import time
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

from canical.commands import COMMANDS
from canical.errors import CanicalError
from canical.files.output_plan import cannot_write, output_plan
from canical.sessions.canlog_format import CANLOG_FORMATS, CANLOG_SUFFIXES, log_format, require_log_support

if TYPE_CHECKING:
    from canical.frames.dbc_files import DbcSet
    from canical.frames.frame_match import FrameMatch, J1939Source

# python-can and cantools are imported where used, so that `--help` answers at once.


def register(sub) -> None:
    p = sub.add_parser("record", help=COMMANDS["record"])
    p.add_argument("-o", "--output", required=True,
                   help=f"CAN log to write, in the format its suffix names ({CANLOG_FORMATS})")
    p.add_argument("--config", help="daemon configuration: interface, channel, DBC and input frames")
    p.add_argument("--interface", help="python-can interface (default: the configuration's)")
    p.add_argument("--channel", help="CAN channel (default: the configuration's)")
    p.add_argument("--dbc", action="append", help="DBC (default: the configuration's; repeatable)")
    p.add_argument("--duration", type=float, help="seconds to record")
    p.add_argument("--frames", type=int, help="stop after this many raw frames")
    p.add_argument("--j1939-source", metavar="ADDR|any",
                   help="J1939 messages are recorded by parameter group from this source address, or any "
                        "[the configuration's j1939.source_address, else the DBC's]")
    p.set_defaults(run=run)


@dataclass(frozen=True)
class Recording:
    """Where to record from and what: the messages (the raw frame first) and their J1939 sources."""

    interface: str
    channel: str
    dbc: DbcSet
    names: list[str]
    j1939_source: J1939Source


def _frames(args: argparse.Namespace) -> Recording:
    """Interface, channel, DBC and the names of the messages to record."""
    from canical.bus.daemon_config import load_config
    from canical.frames.codec import load_dbc
    from canical.frames.dbc_files import dbc_set
    from canical.frames.frame_match import parse_j1939_source
    from canical.sessions.canlog_format import DEFAULT_RAW_MESSAGE, DEFAULT_REF

    interface, channel, names = args.interface, args.channel, [DEFAULT_RAW_MESSAGE]
    dbc = dbc_set(args.dbc) if args.dbc else None
    j1939: J1939Source = None
    if args.config:
        config = load_config(args.config, channel=args.channel)
        interface = interface or config.interface
        channel = channel or config.channel
        dbc = dbc or config.dbc_path
        names = [config.raw_message, *(s.message for s in config.inputs.values())]
        j1939 = config.j1939_source
    if args.j1939_source is not None:
        try:
            j1939 = parse_j1939_source(args.j1939_source, "--j1939-source")
        except ValueError as exc:
            raise CanicalError(str(exc)) from None
    if not (interface and channel and dbc):
        raise CanicalError("record needs --config, or --interface, --channel and --dbc")
    db = load_dbc(dbc)
    known = {m.name: m for m in db.messages}
    raw = known.get(names[0])
    if raw is None:
        raise CanicalError(f"{dbc}: no message {names[0]}")
    if not args.config:  # everything the IMU sends
        names += [m.name for m in db.messages if m.senders == raw.senders]
    ref_message = DEFAULT_REF.split(".")[0]
    if ref_message in known:
        names.append(ref_message)
    return Recording(interface, channel, dbc, list(dict.fromkeys(names)), j1939)


def run(args: argparse.Namespace) -> int:
    from canical.frames.codec import load_dbc
    from canical.frames.frame_match import frame_match

    out = Path(args.output)
    if log_format(out) not in CANLOG_SUFFIXES:
        raise CanicalError(f"{out}: the log must end in one of {CANLOG_FORMATS}")
    if log_format(out) == ".db":
        raise CanicalError(f"{out}: record does not write .db: python-can's SQLite writer can lose the "
                           "frames still queued when recording stops; record .log, .blf or .mf4")
    require_log_support(out)
    what = _frames(args)
    db = load_dbc(what.dbc)
    matches = [frame_match(db.get_message_by_name(n), what.j1939_source) for n in what.names]
    with output_plan(out) as plan:
        recorded = _record(plan.temp_path(out), args, what, matches)
    print(f"record: {recorded['raw']} {what.names[0]} frames, {recorded['all']} frames in all -> {out}")
    return 0


def _record(tmp: Path, args: argparse.Namespace, what: Recording,
            matches: list[FrameMatch]) -> dict[str, int]:
    """Frames into ``tmp`` until the duration, the frame count or a signal; returns the counts.
    On SocketCAN the bus has a receive buffer of seconds of frames, so that writing the log
    loses none meanwhile (:func:`~canical.bus.raw_bus.open_receive_bus`)."""
    import can

    from canical.bus.raw_bus import open_receive_bus

    stop = False

    def on_signal(*_: object) -> None:
        nonlocal stop
        stop = True

    previous = signal.signal(signal.SIGINT, on_signal), signal.signal(signal.SIGTERM, on_signal)
    counts = {"raw": 0, "all": 0}
    interface, channel, names = what.interface, what.channel, what.names
    raw = matches[0]
    try:
        with open_receive_bus(interface, channel, matches) as bus, can.Logger(str(tmp)) as logger:
            print(f"record: {', '.join(names)} on {interface} {channel} -> {args.output} (Ctrl-C ends)",
                  flush=True)
            end = time.monotonic() + args.duration if args.duration else None
            while not stop and (end is None or time.monotonic() < end):
                if args.frames is not None and counts["raw"] >= args.frames:
                    break
                msg = bus.recv(0.2)
                if msg is None or msg.is_error_frame:
                    continue
                logger.on_message_received(msg)
                counts["all"] += 1
                counts["raw"] += raw.matches(msg.arbitration_id, msg.is_extended_id)
    except OSError as exc:
        if exc.filename is not None or exc.errno in (errno.ENOSPC, errno.EDQUOT, errno.EROFS):
            raise cannot_write(args.output, exc.strerror or str(exc)) from None
        raise CanicalError(f"recording from {interface} {channel} failed: {exc}") from None
    except can.CanError as exc:
        raise CanicalError(f"recording from {interface} {channel} failed: {exc}") from None
    finally:
        signal.signal(signal.SIGINT, previous[0])
        signal.signal(signal.SIGTERM, previous[1])
    return counts
