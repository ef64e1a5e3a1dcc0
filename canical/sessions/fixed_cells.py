"""New cells appended to CSV rows held as bytes, numbers formatted as Python's ``f"{x:.6f}"``.

Why: ``canical apply`` writes every input row with its calibrated rate appended, millions of
rows; one Python format per row costs more than reading the file. Here a block of rows gets its
cells in a few numpy passes: the value times 10⁶ rounded to an integer (half to even, as the
correctly rounded decimal Python prints), its digits taken arithmetically, and the bytes placed
by offsets. A value whose product lands too near a half (where the float product could round
the other way than the exact decimal), a huge one or a NaN/infinity is formatted by Python
itself, so every cell is the text ``f"{x:.6f}"`` gives.
"""

from __future__ import annotations

import numpy as np

#: Products below this are exact enough to round: their ulp is at most 1/4.
_EXACT_BELOW = 2.0**50
_COMMA, _NEWLINE, _MINUS, _DOT, _ZERO = 44, 10, 45, 46, 48
#: "000" to "999" as bytes, a row per number: three digits by one look-up.
_DIGITS3 = np.array([[_ZERO + i // 100, _ZERO + i // 10 % 10, _ZERO + i % 10] for i in range(1000)],
                    dtype=np.uint8)


def fixed6_cells(values: np.ndarray) -> np.ndarray:
    """One row of bytes per value: ``f"{x:.6f}"`` left to right, 0 where a row has no byte."""
    v = np.asarray(values, dtype=float)
    with np.errstate(over="ignore", invalid="ignore"):  # those go to Python's format
        q = np.abs(v * 1e6)
    fast = np.isfinite(q) & (q < _EXACT_BELOW)
    q = np.where(fast, q, 0.0)
    fast &= np.abs(q - np.floor(q) - 0.5) > 2.0 * np.spacing(q)
    n = np.rint(q).astype(np.int64)
    whole, frac = np.divmod(n, 1_000_000)
    width = len(str(int(whole.max(initial=0))))
    cells = np.zeros((len(v), 1 + width + 7), dtype=np.uint8)
    cells[:, 0] = np.where(np.signbit(v), _MINUS, 0)
    cells[:, 1 : 1 + width] = _whole_digits(whole, width)
    cells[:, 1 + width] = _DOT
    high, low = np.divmod(frac, 1000)
    cells[:, 2 + width : 5 + width] = _DIGITS3[high]
    cells[:, 5 + width : 8 + width] = _DIGITS3[low]
    slow = np.flatnonzero(~fast)
    if slow.size:
        cells = _python_formatted(cells, v, slow)
    return cells


def _whole_digits(whole: np.ndarray, width: int) -> np.ndarray:
    """The digits of ``whole`` right-aligned in ``width`` bytes, 0 before the first (a 0 shown).

    Three digits at a time from a table: one integer division per three digits, not two per digit.
    """
    groups = -(-width // 3)
    digits = np.empty((len(whole), 3 * groups), dtype=np.uint8)
    rest = whole
    for g in range(groups - 1, -1, -1):
        part = rest
        if g:
            rest, part = np.divmod(rest, 1000)
        digits[:, 3 * g : 3 * g + 3] = _DIGITS3[part]
    shown = np.ones(len(whole), dtype=np.int64)
    for k in range(1, width):
        shown += whole >= 10**k
    power = np.arange(width - 1, -1, -1)
    out: np.ndarray = np.where(power < shown[:, None], digits[:, 3 * groups - width :], 0).astype(np.uint8)
    return out


def _python_formatted(cells: np.ndarray, v: np.ndarray, rows: np.ndarray) -> np.ndarray:
    """``cells`` with ``rows`` replaced by Python's own text (widened if a text is longer)."""
    texts = [f"{x:.6f}".encode("ascii") for x in v[rows].tolist()]
    width = max(cells.shape[1], *(len(t) for t in texts))
    if width > cells.shape[1]:
        cells = np.pad(cells, ((0, 0), (0, width - cells.shape[1])))
    for row, text in zip(rows.tolist(), texts, strict=True):
        cells[row] = 0
        cells[row, : len(text)] = np.frombuffer(text, dtype=np.uint8)
    return cells


def flag_cells(flags: np.ndarray) -> np.ndarray:
    """``0``/``1`` per flag, as ``int(flag)`` prints."""
    out: np.ndarray = (_ZERO + np.asarray(flags, dtype=bool)).astype(np.uint8).reshape(-1, 1)
    return out


def append_cells(rows: bytes, cells: list[np.ndarray]) -> memoryview:
    """``rows`` (each ending in a newline) with ``,cell`` appended to each row for every matrix of
    ``cells`` (one row of bytes per text row, 0 where there is no byte), in order; the bytes as a
    view of the array they were made in (a file writes it as it is: no copy into ``bytes``).

    Why two ways: placing every byte by its own computed offset costs some ten index operations
    per byte of the input, more than reading it. When the rows are of similar lengths (a session's
    are), each row is copied whole into a padded matrix beside its new cells and the padding
    dropped by one mask; a block with a row far longer than the rest takes the byte-offset way.
    """
    buf = np.frombuffer(rows, dtype=np.uint8)
    ends = np.flatnonzero(buf == _NEWLINE)
    n = len(ends)
    if n == 0:
        return memoryview(rows)
    comma = np.full((n, 1), _COMMA, dtype=np.uint8)
    parts = [m for block in cells for m in (comma, block)]
    tails = np.hstack([*parts, np.full((n, 1), _NEWLINE, dtype=np.uint8)])
    starts = np.empty(n, dtype=np.int64)
    starts[0] = 0
    starts[1:] = ends[:-1] + 1
    lengths = ends - starts  # without the newline
    width = int(lengths.max())
    if _PADDED_AT_MOST < 0 or n * (width + 1) > _PADDED_AT_MOST * len(buf) + 4096:
        return _append_scattered(buf, ends, tails)
    return _append_padded(buf, starts, lengths, width, tails)


#: The padded matrix may hold this many times the block's bytes before the byte-offset way is used
#: (negative: always the byte-offset way, for tests).
_PADDED_AT_MOST = 3


def _append_padded(buf: np.ndarray, starts: np.ndarray, lengths: np.ndarray, width: int,
                   tails: np.ndarray) -> memoryview:
    """Each row copied whole (a window of ``width`` bytes from its start), its new cells beside it,
    and the bytes past the row's end and the cells' zeros dropped by one boolean mask."""
    n = len(starts)
    padded = np.zeros(len(buf) + width, dtype=np.uint8)  # every row's window lies inside
    padded[: len(buf)] = buf
    windows = np.lib.stride_tricks.as_strided(padded, shape=(len(buf) + 1, width), strides=(1, 1),
                                              writeable=False)
    full = np.empty((n, width + tails.shape[1]), dtype=np.uint8)
    full[:, :width] = windows[starts]
    full[:, width:] = tails
    keep = np.empty(full.shape, dtype=bool)
    np.less(np.arange(width), lengths[:, None], out=keep[:, :width])
    np.not_equal(tails, 0, out=keep[:, width:])
    return full[keep].data


def _append_scattered(buf: np.ndarray, ends: np.ndarray, tails: np.ndarray) -> memoryview:
    """Every input byte and every new byte placed at its own offset in the output."""
    n = len(ends)
    present = tails != 0
    length = present.sum(axis=1)
    shift = np.concatenate([[0], np.cumsum(length - 1)[:-1]])  # bytes added before each row
    out = np.empty(len(buf) + int(length.sum()) - n, dtype=np.uint8)
    line_lengths = np.diff(np.concatenate([[-1], ends]))
    moved = np.arange(len(buf)) + np.repeat(shift, line_lengths)
    kept = buf != _NEWLINE
    out[moved[kept]] = buf[kept]
    where = (ends + shift)[:, None] + np.cumsum(present, axis=1) - 1
    out[where[present]] = tails[present]
    return out.data
