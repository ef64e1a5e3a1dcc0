"""Read a session too long to hold as means of ``k`` consecutive samples, block by block.

Why: calibration holds its session's columns and works on them whole (plateau finding,
blocks, Allan records), some 90 bytes a sample; fifty million samples would need gigabytes.
Above :data:`REDUCE_ABOVE_ROWS` rows, each run of ``k`` consecutive samples (``k`` the
smallest that brings the rows to the bound) is replaced by its mean as the file is read, so
memory is bounded whatever the session's length. What a mean would hide and calibration
needs is kept: the lowest and highest raw sample behind each row (a row touches a rail when
any of its samples did) and the settled flag (a row is settled when all its samples are).
Time order is checked on the samples themselves, naming the line as the whole read does.
A session within the bound is not touched here (:func:`read_row_means` returns None).
"""

from __future__ import annotations

import os
from collections.abc import Callable

import numpy as np

from canical.errors import CanicalError
from canical.sessions.csv_chunks import CsvHead, check_columns, count_lines, read_chunks, read_head
from canical.sessions.csv_file import TIME_COLUMN, CsvTable
from canical.sessions.session import RowMeans

#: Sessions with more rows than this are read as means (about 300 MB of calibration at most). A
#: mean of a few samples at 1 kHz is a few milliseconds; plateaus and blocks are seconds long.
REDUCE_ABOVE_ROWS = 2_000_000
#: The fewest bytes a session row can take ("0,0,0" and its newline): a file smaller than the
#: bound times this cannot exceed the bound, and its lines are not counted.
MIN_ROW_BYTES = 6


def samples_per_mean(rows: int, bound: int) -> int:
    """The smallest ``k`` whose means of ``rows`` samples number at most ``bound``."""
    return max(1, -(-rows // bound))


def read_row_means(
    path: str | os.PathLike[str],
    *,
    raw_column: str,
    settled_column: str | None = None,
    max_rows: int | None = None,
    on_block: Callable[[int], None] | None = None,
) -> tuple[CsvTable, RowMeans] | None:
    """The file's columns as means of ``k`` samples, with the raw extremes behind each mean;
    None when the file has at most ``max_rows`` rows (default :data:`REDUCE_ABOVE_ROWS`) or a
    head only the whole-file reader reads."""
    bound = max_rows or REDUCE_ABOVE_ROWS
    head = read_head(path)
    if head is None or os.path.getsize(head.path) - head.data_offset <= bound * MIN_ROW_BYTES:
        return None
    lines = count_lines(head)
    if lines <= bound:
        return None
    check_columns(head, [c for c in (raw_column, settled_column) if c])
    reducer = _Reducer(head, lines, samples_per_mean(lines, bound), raw_column, settled_column)
    done = head.data_offset
    for chunk in read_chunks(head, head.header):
        reducer.add(chunk.columns, chunk.first_row)
        done += chunk.size
        if on_block is not None:
            on_block(done)
    return reducer.finish()


#: Rows per mean below which a mean is summed a column at a time (numpy's sum of fewer than eight
#: numbers is the plain sum in order, so the means are the same bits; of more, a pairwise one).
_BY_COLUMNS_BELOW = 8


class _Reducer:
    """Means of ``k`` rows, column by column, written in place into columns sized for the file's
    lines (no copies gathered and joined: memory is the means); the rows short of a whole ``k``
    carried over to the next block."""

    def __init__(self, head: CsvHead, lines: int, k: int, raw_column: str,
                 settled_column: str | None) -> None:
        self.head, self.k = head, k
        self.raw_column, self.settled_column = raw_column, settled_column
        self.names = list(dict.fromkeys(head.header))
        size = -(-lines // k)  # at most: blank lines are not rows
        self.out = {name: np.empty(size) for name in self.names}
        self.low, self.high = np.empty(size), np.empty(size)
        self.filled = 0
        self.rest: dict[str, np.ndarray] = {name: np.zeros(0) for name in self.names}
        self.rows = 0
        self.last_time = -np.inf

    def add(self, columns: dict[str, np.ndarray], first_row: int) -> None:
        self._check_time(columns.get(TIME_COLUMN), first_row)
        self.rows += len(next(iter(columns.values())))
        whole = {name: np.concatenate([self.rest[name], columns[name]]) for name in self.names}
        n = len(whole[self.names[0]])
        cut = n - n % self.k
        at = slice(self.filled, self.filled + cut // self.k)
        for name, values in whole.items():
            self._reduce(name, values[:cut].reshape(-1, self.k), at)
            self.rest[name] = values[cut:]
        self.filled = at.stop

    def finish(self) -> tuple[CsvTable, RowMeans]:
        if self.rest[self.names[0]].size:
            at = slice(self.filled, self.filled + 1)
            for name, values in self.rest.items():
                self._reduce(name, values.reshape(1, -1), at)
            self.filled = at.stop
        n = self.filled
        columns = {name: values[:n] for name, values in self.out.items()}
        means = RowMeans(self.rows, self.k, self.low[:n], self.high[:n])
        head = self.head
        table = CsvTable(head.path, head.meta, head.preamble, head.header, [], columns, head.first_data_line)
        return table, means

    def _reduce(self, name: str, groups: np.ndarray, at: slice) -> None:
        if name == self.settled_column:  # settled when every one of its samples is
            self.out[name][at] = np.all(groups != 0, axis=1)
            return
        if groups.shape[1] >= _BY_COLUMNS_BELOW:
            groups.mean(axis=1, out=self.out[name][at])
            if name == self.raw_column:
                groups.min(axis=1, out=self.low[at])
                groups.max(axis=1, out=self.high[at])
            return
        # A few rows per mean: numpy sums a short row in order from 0.0 (so -0.0 means 0.0);
        # the same sums a column at a time, without a reduction per mean.
        out = self.out[name][at]
        np.add(groups[:, 0], 0.0, out=out)
        for j in range(1, groups.shape[1]):
            out += groups[:, j]
        out /= groups.shape[1]
        if name == self.raw_column:
            for extreme, into in ((np.minimum, self.low[at]), (np.maximum, self.high[at])):
                into[:] = groups[:, 0]
                for j in range(1, groups.shape[1]):
                    extreme(into, groups[:, j], out=into)

    def _check_time(self, time_s: np.ndarray | None, first_row: int) -> None:
        """The whole read's check (``session_from_table``), on the samples before they are averaged."""
        if time_s is None or not time_s.size:
            return
        # One comparison of each sample with the one before (no joined copy, no differences):
        # the line is looked for only when some sample is earlier than the one before it.
        if time_s[0] < self.last_time or bool(np.any(time_s[1:] < time_s[:-1])):
            back = np.flatnonzero(np.diff(np.concatenate([[self.last_time], time_s])) < 0)
            line = self.head.first_data_line + first_row + int(back[0])
            raise CanicalError(f"{self.head.path}: line {line}: time_s goes backwards")
        self.last_time = float(time_s[-1])
