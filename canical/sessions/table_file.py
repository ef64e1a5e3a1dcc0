"""A rate table's own recording of its rate: a CSV (``time_s``, ``ref_dps``) or a CAN log, on its own clock.

Read as it is: times on the table controller's clock (aligned to the sensor's log by
:mod:`.reference_clock`), one row per record, in time order.

Bounded before use: the alignment works on a grid over the file's span, so a clock spanning
1e9 s asked for 149 GiB; rates of 1e300 overflowed in the arithmetic. A span over
:data:`MAX_SPAN_S`, a time or rate that is not finite, or a rate beyond :data:`MAX_RATE_DPS` is
one line naming the row.
"""

from __future__ import annotations

import os

import numpy as np

from canical.errors import CanicalError
from canical.frames.frame_match import J1939Source
from canical.sessions.canlog import read_signal_trace
from canical.sessions.canlog_format import DEFAULT_REF, is_canlog
from canical.sessions.csv_file import TIME_COLUMN, read_table
from canical.sessions.reference_clock import TableTrace

#: The longest table recording aligned: a week (a session is hours; a file of more is not one).
MAX_SPAN_S = 7 * 24 * 3600.0
#: The fastest rate a table reference may give, deg/s (rate tables turn at most a few thousand).
MAX_RATE_DPS = 1e5


def read_table_trace(path: str | os.PathLike[str], *, column: str = "ref_dps",
                     dbc: str | os.PathLike[str] | None = None, signal: str | None = None,
                     j1939_source: J1939Source = None) -> TableTrace:
    """The table's rate and its own times; a CAN log needs the DBC (``signal``: TABLE_REF.TableRate)."""
    name = str(path)
    if is_canlog(path):
        if dbc is None:
            raise CanicalError(f"{name}: reading a CAN log needs --dbc or --config")
        t, ref = read_signal_trace(path, dbc=dbc, signal=signal or DEFAULT_REF, j1939_source=j1939_source)
    else:
        table = read_table(path, [TIME_COLUMN, column])
        t, ref = table.columns[TIME_COLUMN], table.columns[column]
    back = np.flatnonzero(np.diff(t) < 0)
    if back.size:
        i = int(back[0]) + 1
        raise CanicalError(f"{name}: row {i + 1}: time goes backwards ({t[i]:.6g} s after {t[i - 1]:.6g} s)")
    if t.size < 4:
        raise CanicalError(f"{name}: only {t.size} rows: too few to align with the log")
    _check_bounds(name, np.asarray(t, dtype=float), np.asarray(ref, dtype=float))
    return TableTrace(np.asarray(t, dtype=float), np.asarray(ref, dtype=float), name)


def _check_bounds(name: str, t: np.ndarray, ref: np.ndarray) -> None:
    for what, values in (("time", t), ("rate", ref)):
        bad = np.flatnonzero(~np.isfinite(values))
        if bad.size:
            raise CanicalError(f"{name}: row {int(bad[0]) + 1}: {what} is not a finite number")
    fast = np.flatnonzero(np.abs(ref) > MAX_RATE_DPS)
    if fast.size:
        raise CanicalError(f"{name}: row {int(fast[0]) + 1}: rate {ref[fast[0]]:.4g} deg/s is beyond "
                           f"±{MAX_RATE_DPS:g} deg/s: not a table's rate (check the column and unit)")
    span = float(t[-1] - t[0])
    if span > MAX_SPAN_S:
        raise CanicalError(f"{name}: spans {span:.4g} s, more than {MAX_SPAN_S / 86400:g} days: cut it to "
                           "the session's hours, or check the time column's unit")
