"""A session of a gyro triad: the three raw outputs and the table's rate as a vector in IMU axes.

A triad is calibrated from one session per IMU axis: the table turns about one axis (``# axis: x``
in a CSV; ``-x`` when the IMU is mounted upside down, so its x axis points against the table's)
and records all three raw outputs, so the two axes at rest show how much of the turning axis
leaks into them. A multi-axis session (``# axis: multi``, a two- or three-axis table recording
``ref_x_dps``, ``ref_y_dps``, ``ref_z_dps``) is used only to judge the calibration.

CSV form: ``time_s``, ``ref_dps`` (the table's rate about its own axis; a multi-axis session has
the three ``ref_*_dps`` columns instead), ``raw_x``, ``raw_y``, ``raw_z``; every other numeric
column is an auxiliary channel. Errors are one line naming the file.
"""

from __future__ import annotations

import io
import os
from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING

import numpy as np

from canical.errors import CanicalError
from canical.sessions.csv_chunks import read_head
from canical.sessions.csv_file import TIME_COLUMN, read_table
from canical.sessions.session import Session

if TYPE_CHECKING:  # cantools, which the frame module loads, only where frames are read
    from canical.frames.frame_match import J1939Source

AXES = ("x", "y", "z")
RAW_COLUMNS = ("raw_x", "raw_y", "raw_z")
MULTI_REF_COLUMNS = ("ref_x_dps", "ref_y_dps", "ref_z_dps")
MULTI_AXIS = "multi"
REF_COLUMN = "ref_dps"
AXIS_VALUES = "x, y, z, -x, -y, -z or multi"


@dataclass(frozen=True)
class TableAxis:
    """The IMU axis the table turns about, and whether the IMU's axis points along it (+1) or
    against it (-1, mounted upside down)."""

    index: int
    sign: float = 1.0

    @property
    def label(self) -> str:
        return ("-" if self.sign < 0 else "") + AXES[self.index]


def parse_table_axis(text: str, source: str) -> TableAxis | None:
    """``x``, ``-y``... as a table axis; ``multi`` as None (a multi-axis table); else one line."""
    value = text.strip().lower()
    if value == MULTI_AXIS:
        return None
    sign = -1.0 if value.startswith("-") else 1.0
    name = value.lstrip("+-")
    if name not in AXES:
        raise CanicalError(f"{source}: '# axis: {text.strip()}' is not an IMU axis ({AXIS_VALUES})")
    return TableAxis(AXES.index(name), sign)


@dataclass(frozen=True)
class TriadSession:
    """Samples of the three axes in time order; ``rate_dps`` is the true rate vector in IMU axes."""

    time_s: np.ndarray
    raw: np.ndarray  # (n, 3) counts, columns x, y, z
    rate_dps: np.ndarray  # (n, 3) the table's rate in IMU axes
    table_axis: TableAxis | None  # None: a multi-axis table (validation only)
    aux: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict[str, str] = field(default_factory=dict)
    source: str = "<session>"

    def __len__(self) -> int:
        return int(self.raw.shape[0])

    @property
    def sensor_id(self) -> str | None:
        return self.meta.get("sensor")

    @property
    def axis_label(self) -> str:
        return self.table_axis.label if self.table_axis is not None else MULTI_AXIS

    def axis_session(self, index: int) -> Session:
        """Channel ``index`` as a single-axis session, its reference the rate about that IMU axis."""
        meta = {**{k: v for k, v in self.meta.items() if k != "axis"}, "axis": AXES[index]}
        return Session(self.time_s, self.raw[:, index], self.rate_dps[:, index], dict(self.aux), meta)


def read_triad_session(path: str | os.PathLike[str]) -> TriadSession:
    """Read a triad session CSV (see the module's docstring)."""
    name = str(path)
    header = read_head(path) or read_table(path, columns=[])
    if "axis" not in header.meta:
        raise CanicalError(f"{name}: no '# axis:' line naming the IMU axis the table turns about "
                           f"({AXIS_VALUES})")
    axis = parse_table_axis(header.meta["axis"], name)
    refs = [REF_COLUMN] if axis is not None else list(MULTI_REF_COLUMNS)
    for column in (TIME_COLUMN, *refs, *RAW_COLUMNS):
        if column not in header.header:
            raise CanicalError(f"{name}: missing column {column!r} (columns: {', '.join(header.header)})")
    table = read_table(path)
    aux = {c: v for c, v in table.columns.items() if c not in {TIME_COLUMN, *refs, *RAW_COLUMNS}}
    time_s = table.columns[TIME_COLUMN]
    if time_s.size > 1 and np.any(np.diff(time_s) < 0):
        raise CanicalError(f"{name}: time_s goes backwards")
    raw = np.column_stack([table.columns[c] for c in RAW_COLUMNS])
    if axis is None:
        rate = np.column_stack([table.columns[c] for c in MULTI_REF_COLUMNS])
    else:
        rate = np.zeros_like(raw)
        rate[:, axis.index] = axis.sign * table.columns[REF_COLUMN]
    return TriadSession(time_s, raw, rate, axis, aux, dict(table.meta), name)


def read_triad_log(path: str | os.PathLike[str], *, dbc: str | os.PathLike[str], inputs: dict[str, str],
                   ref: str, raw_message: str, raw_signals: dict[str, str],
                   j1939_source: J1939Source = None) -> TriadSession:
    """A triad session recorded on the bus: the three raw signals of the raw frame, the table's
    rate, and the IMU axis it turns about from the table's frame (``TableAxis``, with
    ``TableAxisInverted`` for an IMU mounted upside down); one line when the log has none."""
    from canical.sessions.canlog import read_canlog

    name = str(path)
    logs = [read_canlog(path, dbc=dbc, axis=a, inputs=inputs, ref=ref, raw_message=raw_message,
                        raw_signal=raw_signals.get(a), j1939_source=j1939_source) for a in AXES]
    first = logs[0]
    if first.table_axis is None:
        raise CanicalError(f"{name}: the log has no TableAxis (the table's frame names the IMU axis it "
                           "turns about): a three-axis session needs it")
    sessions = [log.session for log in logs]
    if any(len(s) != len(sessions[0]) for s in sessions):  # the same frames give every axis
        raise CanicalError(f"{name}: the three axes' signals gave different rows")
    axis = TableAxis(AXES.index(first.table_axis), -1.0 if first.table_inverted else 1.0)
    session = sessions[0]
    raw = np.column_stack([s.raw for s in sessions])
    rate = np.zeros_like(raw, dtype=float)
    rate[:, axis.index] = axis.sign * session.reference()
    meta = {k: v for k, v in session.meta.items() if k != "axis"}
    return TriadSession(session.time_s, raw, rate, axis, dict(session.aux), meta, name)


@dataclass(frozen=True)
class UnreferencedTriad:
    """A triad's three raw outputs from a CAN log that carries no table frame: the table's rate
    comes from its own file (``calibrate --reference``), the turning axis from the outputs."""

    time_s: np.ndarray
    raw: np.ndarray  # (n, 3), columns x, y, z
    aux: dict[str, np.ndarray]
    meta: dict[str, str]
    source: str


def read_triad_log_unreferenced(path: str | os.PathLike[str], *, dbc: str | os.PathLike[str],
                                inputs: dict[str, str], raw_message: str, raw_signals: dict[str, str],
                                j1939_source: J1939Source = None) -> UnreferencedTriad:
    """The three raw signals of the raw frame (and the inputs), without a table's rate."""
    from canical.sessions.canlog import read_canlog

    name = str(path)
    sessions = [read_canlog(path, dbc=dbc, axis=a, inputs=inputs, ref=None, raw_message=raw_message,
                            raw_signal=raw_signals.get(a), j1939_source=j1939_source).session for a in AXES]
    if any(len(s) != len(sessions[0]) for s in sessions):  # the same frames give every axis
        raise CanicalError(f"{name}: the three axes' signals gave different rows")
    first = sessions[0]
    meta = {k: v for k, v in first.meta.items() if k != "axis"}
    return UnreferencedTriad(first.time_s, np.column_stack([s.raw for s in sessions]), dict(first.aux), meta,
                             name)


def triad_with_reference(triad: UnreferencedTriad, axis: int, ref_dps: np.ndarray,
                         inside: np.ndarray) -> tuple[TriadSession, float]:
    """The triad session with the table's rate (aligned to its rows) about IMU axis ``axis``,
    the rows the table's file covers; its sign that of the raw output's correlation with the
    table's rate (−: the IMU's axis points against the table's). The correlation is returned."""
    raw = triad.raw[inside]
    ref = np.asarray(ref_dps, dtype=float)[inside]
    if raw.shape[0] < 3 or np.ptp(ref) == 0:
        raise CanicalError(f"{triad.source}: the table's file overlaps too little of the log to tell "
                           "the turning axis's sign")
    r = float(np.corrcoef(raw[:, axis], ref)[0, 1])
    table_axis = TableAxis(axis, -1.0 if r < 0 else 1.0)
    rate = np.zeros_like(raw, dtype=float)
    rate[:, axis] = table_axis.sign * ref
    aux = {k: v[inside] for k, v in triad.aux.items()}
    return TriadSession(triad.time_s[inside], raw, rate, table_axis, aux, dict(triad.meta), triad.source), r


def format_triad_session(session: TriadSession, *, float_format: str = "%.9g") -> str:
    """A triad session as CSV text, in the format :func:`read_triad_session` reads."""
    out = io.StringIO()
    meta = {**session.meta, "axis": session.axis_label}
    for key, value in meta.items():
        out.write(f"# {key}: {value}\n")
    if session.table_axis is not None:
        a = session.table_axis
        names, cols = [TIME_COLUMN, REF_COLUMN], [session.time_s, a.sign * session.rate_dps[:, a.index]]
    else:
        names, cols = [TIME_COLUMN, *MULTI_REF_COLUMNS], [session.time_s, *session.rate_dps.T]
    names += [*RAW_COLUMNS, *session.aux]
    cols += [*session.raw.T, *session.aux.values()]
    out.write(",".join(names) + "\n")
    np.savetxt(out, np.column_stack(cols), delimiter=",", fmt=float_format)
    return out.getvalue()


def check_axes_covered(sessions: Sequence[TriadSession]) -> None:
    """One session per IMU axis x, y, z (either sign); multi-axis sessions are extra.

    Three single-axis sessions about three different axes are independent by construction;
    two about one axis (``x`` and ``-x`` count as one) or a missing axis is one line.
    """
    seen: dict[int, str] = {}
    for s in sessions:
        if s.table_axis is None:
            continue
        i = s.table_axis.index
        if i in seen:
            raise CanicalError(f"{seen[i]} and {s.source} both turn about IMU axis {AXES[i]}: "
                               "give one session per axis")
        seen[i] = s.source
    missing = [AXES[i] for i in range(3) if i not in seen]
    if missing:
        have = ", ".join(AXES[i] for i in sorted(seen)) or "none"
        raise CanicalError(f"the sessions turn about IMU axes {have}: three independent axes are needed, "
                           f"no session for {', '.join(missing)}")
    sensors = {s.sensor_id for s in sessions if s.sensor_id}
    if len(sensors) > 1:
        raise CanicalError(f"the sessions come from different sensors ({', '.join(sorted(sensors))})")
