"""A recorded drive as a CAN log (candump ``.log``, ``.asc``, ``.blf``, ``.trc``, compressed...),
read for ``fleet replay`` a block of rows at a time.

Why the reader ``apply`` uses (:func:`canical.sessions.canlog.stream_canlog`): a drive logged on
the vehicle's bus must give the rows the daemon saw (one per raw frame, every other signal held
at its latest value), and a long log must not be held whole. Why a record of the layout: the
command resolves ``--dbc``/``--config``/``--input`` once; the record travels to the workers with
each task, so a worker reads its log as the command would.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from canical.errors import CanicalError
from canical.frames.dbc_files import DbcSet
from canical.frames.frame_match import J1939Source
from canical.sessions.canlog import stream_canlog
from canical.sessions.canlog_format import HELD_AXIS_PREFIX


@dataclass(frozen=True)
class LogLayout:
    """Where a CAN log's drive columns come from: the DBC files, each channel's signal
    (``speed_mps`` needed; ``temp_c``, ``time_s`` since power-on, ``true_rate_dps`` when mapped),
    the raw message and each axis's raw signal, the J1939 source, and the sensor the logs are of."""

    dbc: DbcSet
    inputs: tuple[tuple[str, str], ...]  # channel -> MESSAGE.Signal
    raw_message: str
    raw_signals: tuple[tuple[str, str], ...]  # axis -> raw signal
    j1939_source: J1939Source
    sensor: str | None

    def check(self, path: Path, needed: tuple[str, ...]) -> None:
        """One line naming the log when a channel it must give is not mapped."""
        inputs = dict(self.inputs)
        missing = [c for c in needed if c not in inputs and c not in ("time_s", "raw")]
        if missing:
            raise CanicalError(f"{path}: a CAN log's drive needs channel {missing[0]!r}: map it with "
                               f"--input {missing[0]}=MESSAGE.Signal or --config")


def log_blocks(path: Path, layout: LogLayout, axis: str, wanted: tuple[str, ...],
               needed: tuple[str, ...]) -> Iterator[dict[str, np.ndarray]]:
    """The log's columns ``time_s``, ``raw`` and those of ``wanted`` it maps, a block at a time
    (without a ``time_s`` input: seconds since the log's first row, one power-on)."""
    layout.check(path, needed)
    inputs = dict(layout.inputs)
    raw_signal = dict(layout.raw_signals).get(axis)
    names = [c for c in wanted if c in inputs]
    if raw_signal is not None and raw_signal.startswith(HELD_AXIS_PREFIX) and raw_signal in inputs:
        names.append(raw_signal)
    stream = stream_canlog(path, dbc=layout.dbc, axis=axis, inputs={n: inputs[n] for n in names},
                           raw_message=layout.raw_message, raw_signal=raw_signal, sensor=layout.sensor,
                           j1939_source=layout.j1939_source)
    for block in stream.blocks():
        yield {"time_s": block.time_s, "raw": block.raw, **block.aux}
