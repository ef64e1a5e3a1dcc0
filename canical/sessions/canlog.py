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

import math
import os
from collections.abc import Iterator, Mapping
from dataclasses import dataclass, field
from pathlib import Path

import can
import numpy as np
from cantools.database.can import Database, Message, Signal

from canical.errors import CanicalError
from canical.frames.codec import load_dbc
from canical.frames.frame_match import FrameMatch, FrameMatcher, J1939Source, frame_match
from canical.sessions.canlog_format import (
    DEFAULT_RAW_MESSAGE,
    DEFAULT_REF,
    HELD_AXIS_PREFIX,
    held_complaints,
    require_log_support,
)
from canical.sessions.session import RAW_UNITS, Rail, Session

TIME_INPUT = "time_s"
TABLE_AXIS = "TABLE_REF.TableAxis"
TABLE_INVERTED = "TABLE_REF.TableAxisInverted"
TABLE_SETTLED = "TABLE_REF.TableSettled"


@dataclass(frozen=True)
class CanlogSession:
    """A session read from a log, and what reading it left out."""

    session: Session
    frames: int  # frames in the log
    skipped: int  # raw frames before every needed signal had a value
    dropped: int  # frames the daemon would drop: error, remote, FD, wrong length
    table_axis: str | None  # the axis the rate table reports turning, if it says
    table_inverted: bool = False  # ... and that the IMU's axis points against it (mounted upside down)


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


FrameKey = tuple[int, bool]  # arbitration id, extended
FrameEntry = tuple[Message, list[tuple[str, str]]]  # a message and its (channel, signal)s
FrameMap = dict[FrameKey, FrameEntry]


@dataclass
class _LogRows:
    """One row per raw frame once every needed signal has a value; the others held as of it."""

    channels: list[str]  # the session's channels, in order
    needed: list[str]  # signals a row cannot be made without
    has_ref: bool
    held: dict[str, float] = field(default_factory=dict)
    times: list[float] = field(default_factory=list)
    frame_no: list[int] = field(default_factory=list)
    settled: list[float] = field(default_factory=list)
    raws: list[float] = field(default_factory=list)
    rows: list[list[float]] = field(default_factory=list)
    refs: list[float] = field(default_factory=list)
    frames: int = 0
    skipped: int = 0
    dropped: int = 0

    def hold(self, values: Mapping[str, object], pairs: list[tuple[str, str]]) -> None:
        for channel, sig in pairs:
            self.held[channel] = _number(values, sig)

    def add(self, timestamp: float, raw: float) -> None:
        """A raw frame: a row, or skipped while a needed signal has not been seen."""
        if any(c not in self.held for c in self.needed):
            self.skipped += 1
            return
        self.times.append(timestamp)
        self.frame_no.append(self.frames)
        self.settled.append(self.held.get("\0settled", 1.0))
        self.raws.append(raw)
        self.rows.append([self.held[c] for c in self.channels])
        if self.has_ref:
            self.refs.append(self.held["\0ref"])

    def drain(self) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        """The rows made so far (timestamps, raw values, channels as columns), and forget them."""
        data = np.asarray(self.rows, dtype=float).reshape(len(self.raws), len(self.channels))
        out = np.asarray(self.times, dtype=float), np.asarray(self.raws, dtype=float), data
        self.times, self.frame_no, self.settled, self.raws, self.rows, self.refs = [], [], [], [], [], []
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
    j1939_source: J1939Source = None,
) -> CanlogSession:
    """One axis of a CAN log as a session.

    ``inputs`` maps channel names to ``MESSAGE.Signal``; the name ``time_s`` becomes the
    session's time (else frame timestamps relative to the first raw frame are used).
    ``ref`` is the table's rate signal (None for field data, which has no reference).
    J1939 messages are matched by their parameter group (:mod:`canical.frames.frame_match`)
    and ``j1939_source``.
    """
    reader = _LogReader(path, dbc=dbc, axis=axis, inputs=inputs, ref=ref, raw_message=raw_message,
                        raw_signal=raw_signal, j1939_source=j1939_source)
    log = reader.log
    for _ in reader.frames():
        pass
    signal = reader.signal
    rail = signal_rail(signal, f"DBC signal {reader.signal_where}")
    session = _session(log, reader.name, reader.raw.name, axis, sensor, rail, signal.unit or None)
    for channel in [c for c in session.aux if c.startswith(HELD_AXIS_PREFIX)]:
        del session.aux[channel]  # axes' raw values, not inputs
    return CanlogSession(session, log.frames, log.skipped, log.dropped, _table_axis(log.held),
                         bool(log.held.get("\0inverted", 0.0)))


class _LogReader:
    """A log's frames taken one by one as the daemon takes them, into :class:`_LogRows`: the DBC's
    messages and signals looked up once, the frames read through python-can."""

    def __init__(self, path: str | os.PathLike[str], *, dbc: str | os.PathLike[str], axis: str,
                 inputs: Mapping[str, str], ref: str | None, raw_message: str, raw_signal: str | None,
                 j1939_source: J1939Source) -> None:
        self.name = str(path)
        if not Path(path).is_file():
            raise CanicalError(f"{self.name}: file not found")
        require_log_support(path)
        db = load_dbc(dbc)
        self.raw = raw = _message(db, raw_message, dbc)
        self.raw_sig = raw_sig = raw_signal or f"GyroRaw{axis.upper()}"
        if raw_sig.startswith(HELD_AXIS_PREFIX):  # in another message: held, taken at each raw frame
            if raw_sig not in inputs:
                raise CanicalError(f"axis {axis}: its raw signal ({raw_sig}) is not among the inputs")
            held_msg, _, held_sig = inputs[raw_sig].partition(".")
            signal_msg, signal_name = _message(db, held_msg, dbc), held_sig
        elif raw_sig not in {s.name for s in raw.signals}:
            raise CanicalError(f"{dbc}: message {raw.name} has no signal {raw_sig} (axis {axis})")
        else:
            signal_msg, signal_name = raw, raw_sig
        self.signal = signal_msg.get_signal_by_name(signal_name)
        self.signal_where = f"{signal_msg.name}.{signal_name}"
        wanted = _wanted_signals(db, inputs, ref)
        by_id = _frames_by_id(db, dbc, wanted)
        self.raw_match = frame_match(raw, j1939_source)
        self.raw_entry = (raw, by_id.pop((raw.frame_id, raw.is_extended_frame), (raw, []))[1])
        self.others = FrameMatcher((frame_match(msg, j1939_source), (msg, pairs))
                                   for msg, pairs in by_id.values())
        self.log = _LogRows(channels=[c for c in wanted if not c.startswith("\0")],
                            needed=[c for c in wanted if c not in ("\0axis", "\0settled", "\0inverted")],
                            has_ref=ref is not None)

    def frames(self) -> Iterator[None]:
        """Each frame of the log taken in turn (a step per frame, so a caller may take the rows
        made so far between two)."""
        try:
            with held_complaints() as complaints:
                for frame in can.LogReader(self.name):
                    _take_frame(self.log, frame, self.raw_match, self.raw_entry, self.raw_sig, self.others)
                    yield None
            complaints.check(self.name, self.log.frames)
        except CanicalError:
            raise
        except Exception as exc:  # python-can's readers raise many types on a damaged file
            raise CanicalError(f"{self.name}: cannot read CAN log after {self.log.frames} frames ({exc})") \
                from None


@dataclass(frozen=True)
class CanlogBlock:
    """Consecutive rows of a log, as :func:`read_canlog`'s session holds them: time (the
    ``time_s`` input, else seconds since the first row), raw values and the inputs."""

    time_s: np.ndarray
    raw: np.ndarray
    aux: dict[str, np.ndarray]


@dataclass
class CanlogStream:
    """One axis of a log without a reference, read a block of rows at a time (``blocks``), for a
    log too long to hold: memory is the block's. After the blocks, the counts of what was read.

    The rows, joined, are those of :func:`read_canlog`'s session (``ref=None``); a log with no
    row at all is refused as it refuses it, after the last frame.
    """

    reader: _LogReader
    axis: str
    sensor: str | None
    rows_per_block: int

    @property
    def meta(self) -> dict[str, str]:
        """The metadata :func:`read_canlog`'s session has."""
        meta = {"axis": self.axis, "source": Path(self.reader.name).name}
        if self.sensor:
            meta = {"sensor": self.sensor, **meta}
        if self.reader.signal.unit:
            meta[RAW_UNITS] = self.reader.signal.unit
        return meta

    @property
    def channels(self) -> list[str]:
        """The session's aux columns, in order."""
        return [c for c in self.reader.log.channels if c != TIME_INPUT and not c.startswith(HELD_AXIS_PREFIX)]

    @property
    def frames(self) -> int:
        return self.reader.log.frames

    @property
    def skipped(self) -> int:
        return self.reader.log.skipped

    def blocks(self) -> Iterator[CanlogBlock]:
        log = self.reader.log
        first: float | None = None
        rows = 0
        for _ in self.reader.frames():
            if len(log.raws) >= self.rows_per_block:
                first, block = self._block(first)
                rows += len(block.raw)
                yield block
        if log.raws:
            first, block = self._block(first)
            rows += len(block.raw)
            yield block
        if not rows:
            _session(log, self.reader.name, self.reader.raw.name, self.axis, self.sensor, None, None)

    def _block(self, first: float | None) -> tuple[float, CanlogBlock]:
        times, raw, data = self.reader.log.drain()
        aux = {c: data[:, i] for i, c in enumerate(self.reader.log.channels)}
        first = float(times[0]) if first is None else first
        time_s = aux.pop(TIME_INPUT) if TIME_INPUT in aux else times - first
        return first, CanlogBlock(time_s, raw, {c: aux[c] for c in self.channels})


def stream_canlog(
    path: str | os.PathLike[str],
    *,
    dbc: str | os.PathLike[str],
    axis: str,
    inputs: Mapping[str, str],
    raw_message: str = DEFAULT_RAW_MESSAGE,
    raw_signal: str | None = None,
    sensor: str | None = None,
    j1939_source: J1939Source = None,
    rows_per_block: int | None = None,
) -> CanlogStream:
    """:func:`read_canlog` (without a reference) as a stream of blocks of rows (of
    :data:`BLOCK_ROWS` by default): the DBC and the mapping checked now, the frames read as the
    blocks are taken."""
    reader = _LogReader(path, dbc=dbc, axis=axis, inputs=inputs, ref=None, raw_message=raw_message,
                        raw_signal=raw_signal, j1939_source=j1939_source)
    return CanlogStream(reader, axis, sensor, rows_per_block or BLOCK_ROWS)


#: Rows per block of a streamed log: some megabytes of rows held as Python lists while it is read.
BLOCK_ROWS = 1 << 16


def signal_rail(signal: Signal, where: str) -> Rail | None:
    """The physical limits a DBC signal can carry: its bit width through its scale and offset,
    narrowed by a declared minimum/maximum. None for a float signal (no converter rail to see)."""
    if signal.is_float:
        return None
    n = signal.length
    lo_raw, hi_raw = (-(1 << (n - 1)), (1 << (n - 1)) - 1) if signal.is_signed else (0, (1 << n) - 1)
    scale, offset = float(signal.scale), float(signal.offset)
    low, high = sorted((offset + scale * lo_raw, offset + scale * hi_raw))
    what = f"{n}-bit {'signed' if signal.is_signed else 'unsigned'}, scale {scale:g}"
    declared_lo, declared_hi = signal.minimum, signal.maximum
    if declared_lo is not None and declared_hi is not None and declared_lo < declared_hi \
            and (declared_lo > low or declared_hi < high):
        low, high = max(low, float(declared_lo)), min(high, float(declared_hi))
        what += f", declared {declared_lo:g} to {declared_hi:g}"
    return Rail(low, high, f"{where}: {what}", abs(scale))


def _wanted_signals(db: Database, inputs: Mapping[str, str], ref: str | None) -> dict[str, str]:
    """Channel -> ``MESSAGE.Signal`` of everything to hold: the inputs, the reference and, when the
    DBC has the table's message, its axis and (with its rate) its settled flag, as ``\0`` names."""
    wanted = dict(inputs)
    if ref is not None:
        wanted["\0ref"] = ref
    if TABLE_AXIS.split(".")[0] in {m.name for m in db.messages}:
        wanted.setdefault("\0axis", TABLE_AXIS)
        table_signals = {sg.name for sg in db.get_message_by_name(TABLE_AXIS.split(".")[0]).signals}
        if TABLE_INVERTED.split(".")[1] in table_signals:
            wanted.setdefault("\0inverted", TABLE_INVERTED)
        if ref == DEFAULT_REF and TABLE_SETTLED.split(".")[1] in table_signals:
            wanted.setdefault("\0settled", TABLE_SETTLED)  # the table's own flag goes with its rate
    return wanted


def _frames_by_id(db: Database, dbc: str | os.PathLike[str], wanted: Mapping[str, str]) -> FrameMap:
    """Frame id -> (message, [(channel, signal)]) of the wanted signals, each checked in the DBC."""
    by_id: FrameMap = {}
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
    return by_id


def _take_frame(log: _LogRows, frame: can.Message, raw_match: FrameMatch, raw: FrameEntry, raw_sig: str,
                others: FrameMatcher[FrameEntry]) -> None:
    """One frame of the log, as the daemon takes it: dropped, a row (a raw frame), held, or ignored."""
    log.frames += 1
    if frame.is_error_frame or frame.is_remote_frame or frame.is_fd:
        log.dropped += 1
        return
    is_raw = raw_match.matches(frame.arbitration_id, frame.is_extended_id)
    entry = raw if is_raw else others.get(frame.arbitration_id, frame.is_extended_id)
    if entry is None:
        return
    msg_def, pairs = entry
    if len(frame.data) != msg_def.length:
        log.dropped += 1
        return
    values = _signals(msg_def, frame.data)
    log.hold(values, pairs)
    if is_raw:
        held = raw_sig.startswith(HELD_AXIS_PREFIX)
        log.add(float(frame.timestamp), log.held.get(raw_sig, math.nan) if held else _number(values, raw_sig))


def _session(log: _LogRows, name: str, raw_name: str, axis: str, sensor: str | None,
             rail: Rail | None, raw_units: str | None) -> Session:
    """The rows as a session: in time order when it has a reference (a drive is corrected as is)."""
    if not log.raws:
        what = f"{raw_name} frames" if log.frames else "frames"
        missing = [c.strip(chr(0)) or "ref" for c in log.needed]
        extra = f" with {', '.join(missing)} seen" if log.needed else ""
        hint = ("; the table's rate: map it with --input ref_dps=MESSAGE.Signal, or give the table's own "
                "file with --reference" if "ref" in missing else "")
        raise CanicalError(f"{name}: no {what}{extra} in {log.frames} frames{hint}")
    data = np.asarray(log.rows, dtype=float).reshape(len(log.raws), len(log.channels))
    aux = {c: data[:, i] for i, c in enumerate(log.channels)}
    t = np.asarray(log.times)
    back = np.flatnonzero(np.diff(t) < 0)
    if log.has_ref and back.size:
        i = int(back[0]) + 1
        raise CanicalError(f"{name}: frame {log.frame_no[i]}: timestamp goes backwards "
                           f"({t[i]:.6f} after {t[i - 1]:.6f})")
    time_s = aux.pop(TIME_INPUT) if TIME_INPUT in aux else t - t[0]
    meta = {"axis": axis, "source": Path(name).name}
    if sensor:
        meta = {"sensor": sensor, **meta}
    if raw_units:  # "raw" is the signal's physical value: the set says in which unit
        meta[RAW_UNITS] = raw_units
    return Session(
        time_s=time_s,
        raw=np.asarray(log.raws),
        ref_dps=np.asarray(log.refs) if log.has_ref else None,
        aux=aux,
        meta=meta,
        settled=np.asarray(log.settled) != 0 if "\0settled" in log.held else None,
        rail=rail,
    )


def _table_axis(held: Mapping[str, float]) -> str | None:
    """The axis the table last reported turning, if it reports one."""
    axis_code = held.get("\0axis")
    return {0: "x", 1: "y", 2: "z"}.get(int(axis_code)) if axis_code is not None else None


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


def read_signal_trace(path: str | os.PathLike[str], *, dbc: str | os.PathLike[str],
                      signal: str, j1939_source: J1939Source = None) -> tuple[np.ndarray, np.ndarray]:
    """(frame timestamps, values) of one ``MESSAGE.Signal`` in a log, on the log's own clock.

    For a table controller's own log: every frame of the message is a row, as recorded.
    """
    name = str(path)
    if not Path(path).is_file():
        raise CanicalError(f"{name}: file not found")
    require_log_support(path)
    db = load_dbc(dbc)
    msg_name, _, sig_name = signal.partition(".")
    msg = _message(db, msg_name, dbc)
    if sig_name not in {s.name for s in msg.signals}:
        raise CanicalError(f"{dbc}: message {msg_name} has no signal {sig_name}")
    match = frame_match(msg, j1939_source)
    times: list[float] = []
    values: list[float] = []
    frames = 0
    try:
        with held_complaints() as complaints:
            for frame in can.LogReader(name):
                frames += 1
                if frame.is_error_frame or frame.is_remote_frame or frame.is_fd \
                        or not match.matches(frame.arbitration_id, frame.is_extended_id) \
                        or len(frame.data) != msg.length:
                    continue
                times.append(float(frame.timestamp))
                values.append(_number(_signals(msg, frame.data), sig_name))
        complaints.check(name, frames)
    except CanicalError:
        raise
    except Exception as exc:  # python-can's readers raise many types on a damaged file
        raise CanicalError(f"{name}: cannot read CAN log ({exc})") from None
    if not times:
        raise CanicalError(f"{name}: no {msg_name} frames")
    return np.asarray(times), np.asarray(values)
