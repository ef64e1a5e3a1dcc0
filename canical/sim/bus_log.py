"""Simulated samples as the frames a vendor's IMU would send, in the layout of the user's own DBC.

Why: a user without hardware wants to try every feature (calibrating from a log, ``apply`` on a
drive, ``--track-bias``, three axes) on the layout of the IMU they will buy, not on canical's
own frames. A sample becomes one frame of the raw message (every axis's signal; the message's
other signals at 0), the channels the configuration maps (``temp_c``, ``time_s``, a speed) go in
their own messages at :data:`CHANNEL_RATE_HZ`, and a turntable's rate goes in canical's
``TABLE_REF``, as ``canical record`` would find them on the bus.
"""

from __future__ import annotations

from collections.abc import Iterator, Mapping
from dataclasses import dataclass

import can
import numpy as np
from cantools.database.can import Database, Message

#: How often a channel's message is sent: a temperature or a speed changes slowly.
CHANNEL_RATE_HZ = 10.0
#: canical's table reference frame and its signals (``dbc/canical.dbc``).
TABLE_REF = "TABLE_REF"
AXES = ("x", "y", "z")


@dataclass(frozen=True)
class SignalTrack:
    """One signal's values, one per sample (the raw axes) or per channel frame."""

    message: Message
    signal: str
    values: np.ndarray
    #: The id its frames go out with (None: the DBC's): a J1939 IMU's claimed source address in it.
    arbitration_id: int | None = None


@dataclass(frozen=True)
class LogPlan:
    """What a simulated log holds: the raw message's signals per sample, the channels, the table."""

    time_s: np.ndarray
    raw: tuple[SignalTrack, ...]  # one per axis sent, all of one message
    channels: tuple[SignalTrack, ...]
    table: tuple[SignalTrack, ...] = ()  # TABLE_REF's signals per sample (a turntable session)


def table_tracks(db: Database, ref_dps: np.ndarray, axis_index: int, settled: np.ndarray,
                 inverted: bool = False) -> tuple[SignalTrack, ...]:
    """canical's ``TABLE_REF`` per sample, as a table on the bus sends it: its rate, the IMU axis
    it turns about (and whether the IMU is mounted against it), its settled flag."""
    ref = db.get_message_by_name(TABLE_REF)
    n = len(ref_dps)
    return (SignalTrack(ref, "TableRate", np.asarray(ref_dps, dtype=float)),
            SignalTrack(ref, "TableAxis", np.full(n, float(axis_index))),
            SignalTrack(ref, "TableSettled", np.asarray(settled, dtype=float)),
            SignalTrack(ref, "TableAxisInverted", np.full(n, float(inverted))))


def physical(message: Message, signal: str, values: np.ndarray) -> np.ndarray:
    """Values as the signal can carry them: rounded to its scale, clipped to its range."""
    sig = message.get_signal_by_name(signal)
    scale, offset = float(sig.conversion.scale), float(sig.conversion.offset)
    steps = np.round((np.asarray(values, dtype=float) - offset) / scale)
    bits = sig.length
    lo, hi = (-(2 ** (bits - 1)), 2 ** (bits - 1) - 1) if sig.is_signed else (0, 2**bits - 1)
    out = np.clip(steps, lo, hi) * scale + offset
    if sig.minimum is not None and sig.maximum is not None:
        out = np.clip(out, float(sig.minimum), float(sig.maximum))
    return out


def _encode(message: Message, values: Mapping[str, float]) -> bytes:
    data: dict[str, float] = {s.name: 0.0 for s in message.signals}
    data.update(values)
    return bytes(message.encode(data, scaling=True, strict=False))


def _frames(track_group: tuple[SignalTrack, ...], time_s: np.ndarray,
            rows: np.ndarray) -> Iterator[can.Message]:
    message = track_group[0].message
    frame_id = track_group[0].arbitration_id
    for k, i in enumerate(rows):
        payload = _encode(message, {t.signal: float(t.values[k]) for t in track_group})
        yield can.Message(timestamp=float(time_s[i]),
                          arbitration_id=message.frame_id if frame_id is None else frame_id,
                          is_extended_id=bool(message.is_extended_frame), data=payload)


def messages(plan: LogPlan, t0: float = 1_700_000_000.0) -> list[can.Message]:
    """Every frame of the plan in time order (channel and table frames just before a raw frame)."""
    n = len(plan.time_s)
    stamps = t0 + plan.time_s
    channel_rows = np.arange(0, n, channel_every(plan.time_s))
    out: list[tuple[float, int, can.Message]] = []
    for order, (group, rows) in enumerate([(plan.table, np.arange(n)), *(
            ((t,), channel_rows) for t in plan.channels)]):
        if group:
            out += [(m.timestamp, order, m) for m in _frames(group, stamps - 1e-4, rows)]
    out += [(m.timestamp, 99, m) for m in _frames(plan.raw, stamps, np.arange(n))]
    out.sort(key=lambda e: (e[0], e[1]))
    return [m for _, _, m in out]


def channel_every(time_s: np.ndarray) -> int:
    """A channel frame every this many samples (:data:`CHANNEL_RATE_HZ`)."""
    if len(time_s) < 2:
        return 1
    return max(1, round(1.0 / (CHANNEL_RATE_HZ * float(np.median(np.diff(time_s))))))


def decimate(values: np.ndarray, time_s: np.ndarray) -> np.ndarray:
    """The values at the channel frames' samples (see :func:`messages`)."""
    return np.asarray(values)[:: channel_every(time_s)]
