"""Sessions from CAN logs decoded with the DBC: every format python-can's ``LogReader`` reads.

Formats: candump ``.log``, Vector ``.asc`` and ``.blf``, PEAK ``.trc``, python-can's ``.csv``
and SQLite ``.db``, ASAM MDF4 ``.mf4`` (with the optional ``asammdf``), each also gzip-compressed
(``.asc.gz``). They are read through python-can, never parsed here, so a logger's format is
python-can's job. A ``.csv`` is a CAN log only when it has python-can's header; any other CSV
is a session CSV.

Why: a turntable session recorded from the bus (the IMU's raw frames and the table's
reference frames) should calibrate directly, and a drive recorded from the bus should be
correctable offline exactly as the daemon corrects it live. So the rules are the daemon's:
one sample per raw frame of the IMU; every other signal (the table's rate, temperature,
uptime...) is held at its latest value as of that frame; frames the daemon would drop
(error, remote, CAN FD, wrong length) are dropped here too. Samples before every needed
signal has been seen once are left out (and counted), as there is nothing to hold yet.
"""

from __future__ import annotations

import os
from collections.abc import Mapping
from dataclasses import dataclass
from pathlib import Path

import can
import numpy as np
from cantools.database.can import Database, Message

from canical.errors import CanicalError
from canical.frames.codec import load_dbc
from canical.sessions.canlog_format import DEFAULT_RAW_MESSAGE, DEFAULT_REF, require_log_support
from canical.sessions.session import Session

TIME_INPUT = "time_s"
TABLE_AXIS = "TABLE_REF.TableAxis"
TABLE_SETTLED = "TABLE_REF.TableSettled"


@dataclass(frozen=True)
class CanlogSession:
    """A session read from a log, and what reading it left out."""

    session: Session
    frames: int  # frames in the log
    skipped: int  # raw frames before every needed signal had a value
    dropped: int  # frames the daemon would drop: error, remote, FD, wrong length
    table_axis: str | None  # the axis the rate table reports turning, if it says


def parse_signal_map(items: list[str] | None) -> dict[str, str]:
    """``NAME=MESSAGE.Signal`` command-line items as a dict."""
    out: dict[str, str] = {}
    for item in items or []:
        name, sep, ref = item.partition("=")
        if not sep or not name or ref.count(".") != 1:
            raise CanicalError(f"--input {item!r}: expected NAME=MESSAGE.Signal")
        out[name.strip()] = ref.strip()
    return out


def default_inputs(
    dbc_path: str | os.PathLike[str], raw_message: str = DEFAULT_RAW_MESSAGE
) -> dict[str, str]:
    """Auxiliary channels when none are named: the environment the raw frame's node reports.

    Every signal with a unit from that node, named by signal (``Temperature``,
    ``SupplyVoltage``...), except what is not environment: gyro outputs (raw counts, rates
    in deg/s), time (seconds: ``time_s`` is mapped explicitly) and unitless counters and flags.
    """
    db = load_dbc(dbc_path)
    raw = _message(db, raw_message, dbc_path)
    not_environment = {s.unit for s in raw.signals if s.name.startswith("GyroRaw")} | {"deg/s", "s"}
    out: dict[str, str] = {}
    for msg in db.messages:
        if msg.senders != raw.senders or msg.is_multiplexed():
            continue
        for sig in msg.signals:
            if sig.unit and sig.unit not in not_environment:
                out[sig.name] = f"{msg.name}.{sig.name}"
    return out


def read_canlog(
    path: str | os.PathLike[str],
    *,
    dbc: str | os.PathLike[str],
    axis: str,
    inputs: Mapping[str, str],
    ref: str | None = DEFAULT_REF,
    raw_message: str = DEFAULT_RAW_MESSAGE,
    raw_signal: str | None = None,
    sensor: str | None = None,
) -> CanlogSession:
    """One axis of a CAN log as a session.

    ``inputs`` maps channel names to ``MESSAGE.Signal``; the name ``time_s`` becomes the
    session's time (else frame timestamps relative to the first raw frame are used).
    ``ref`` is the table's rate signal (None for field data, which has no reference).
    """
    name = str(path)
    if not Path(path).is_file():
        raise CanicalError(f"{name}: file not found")
    require_log_support(path)
    db = load_dbc(dbc)
    raw = _message(db, raw_message, dbc)
    raw_sig = raw_signal or f"GyroRaw{axis.upper()}"
    if raw_sig not in {s.name for s in raw.signals}:
        raise CanicalError(f"{dbc}: message {raw.name} has no signal {raw_sig} (axis {axis})")
    wanted = dict(inputs)
    if ref is not None:
        wanted["\0ref"] = ref
    if TABLE_AXIS.split(".")[0] in {m.name for m in db.messages}:
        wanted.setdefault("\0axis", TABLE_AXIS)
        table_signals = {sg.name for sg in db.get_message_by_name(TABLE_AXIS.split(".")[0]).signals}
        if ref == DEFAULT_REF and TABLE_SETTLED.split(".")[1] in table_signals:
            wanted.setdefault("\0settled", TABLE_SETTLED)  # the table's own flag goes with its rate
    # frame id -> (message, [(channel, signal)])
    by_id: dict[tuple[int, bool], tuple[Message, list[tuple[str, str]]]] = {}
    for channel, sref in wanted.items():
        msg_name, _, sig_name = sref.partition(".")
        msg = _message(db, msg_name, dbc)
        if sig_name not in {s.name for s in msg.signals}:
            label = channel.strip("\0")
            raise CanicalError(f"{dbc}: message {msg_name} has no signal {sig_name} (for {label})")
        if msg.is_multiplexed():
            raise CanicalError(f"{sref}: multiplexed messages are not supported as channels")
        key = (msg.frame_id, msg.is_extended_frame)
        by_id.setdefault(key, (msg, []))[1].append((channel, sig_name))
    raw_key = (raw.frame_id, raw.is_extended_frame)
    raw_pairs = by_id.pop(raw_key, (raw, []))[1]

    held: dict[str, float] = {}
    channels = [c for c in wanted if not c.startswith("\0")]
    needed = [c for c in wanted if c not in ("\0axis", "\0settled")]
    times: list[float] = []
    frame_no: list[int] = []
    settled: list[float] = []
    raws: list[float] = []
    rows: list[list[float]] = []
    refs: list[float] = []
    frames = skipped = dropped = 0
    try:
        reader = can.LogReader(name)
        for frame in reader:
            frames += 1
            if frame.is_error_frame or frame.is_remote_frame or frame.is_fd:
                dropped += 1
                continue
            key = (frame.arbitration_id, frame.is_extended_id)
            if key == raw_key:
                if len(frame.data) != raw.length:
                    dropped += 1
                    continue
                values = _signals(raw, frame.data)
                for channel, sig in raw_pairs:
                    held[channel] = _number(values, sig)
                if any(c not in held for c in needed):
                    skipped += 1
                    continue
                times.append(float(frame.timestamp))
                frame_no.append(frames)
                settled.append(held.get("\0settled", 1.0))
                raws.append(_number(values, raw_sig))
                rows.append([held[c] for c in channels])
                if ref is not None:
                    refs.append(held["\0ref"])
                continue
            entry = by_id.get(key)
            if entry is None:
                continue
            msg_def, pairs = entry
            if len(frame.data) != msg_def.length:
                dropped += 1
                continue
            values = _signals(msg_def, frame.data)
            for channel, sig in pairs:
                held[channel] = _number(values, sig)
    except CanicalError:
        raise
    except Exception as exc:  # python-can's readers raise many types on a damaged file
        raise CanicalError(f"{name}: cannot read CAN log after {frames} frames ({exc})") from None
    if not raws:
        what = f"{raw.name} frames" if frames else "frames"
        extra = f" with {', '.join(c.strip(chr(0)) or 'ref' for c in needed)} seen" if needed else ""
        raise CanicalError(f"{name}: no {what}{extra} in {frames} frames")
    data = np.asarray(rows, dtype=float).reshape(len(raws), len(channels))
    aux = {c: data[:, i] for i, c in enumerate(channels)}
    t = np.asarray(times)
    back = np.flatnonzero(np.diff(t) < 0)
    if ref is not None and back.size:  # a session must be in time order; a drive is corrected as is
        i = int(back[0]) + 1
        raise CanicalError(f"{name}: frame {frame_no[i]}: timestamp goes backwards "
                           f"({t[i]:.6f} after {t[i - 1]:.6f})")
    time_s = aux.pop(TIME_INPUT) if TIME_INPUT in aux else t - t[0]
    axis_code = held.get("\0axis")
    table_axis = {0: "x", 1: "y", 2: "z"}.get(int(axis_code)) if axis_code is not None else None
    meta = {"axis": axis, "source": Path(name).name}
    if sensor:
        meta = {"sensor": sensor, **meta}
    session = Session(
        time_s=time_s,
        raw=np.asarray(raws),
        ref_dps=np.asarray(refs) if ref is not None else None,
        aux=aux,
        meta=meta,
        settled=np.asarray(settled) != 0 if "\0settled" in held else None,
    )
    return CanlogSession(session, frames, skipped, dropped, table_axis)


def _signals(message: Message, data: bytearray) -> Mapping[str, object]:
    """A frame's signals by name, choices as their numbers (the log's own frame, unmultiplexed)."""
    values = message.decode(bytes(data), decode_choices=False)
    if not isinstance(values, Mapping):  # only container messages decode to a list of parts
        raise CanicalError(f"message {message.name}: container messages are not supported")
    return values


def _number(values: Mapping[str, object], signal: str) -> float:
    """One signal's value; without choices cantools decodes every signal to an int or a float."""
    value = values[signal]
    if not isinstance(value, int | float):
        raise CanicalError(f"signal {signal} decodes to {value!r}, not a number")
    return float(value)


def _message(db: Database, name: str, dbc: str | os.PathLike[str]) -> Message:
    try:
        return db.get_message_by_name(name)
    except KeyError:
        raise CanicalError(f"{dbc}: no message {name}") from None
