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
    digits = 1 + sum((whole >= 10**k).astype(np.int64) for k in range(1, width))
    cells = np.zeros((len(v), 1 + width + 7), dtype=np.uint8)
    cells[:, 0] = np.where(np.signbit(v), _MINUS, 0)
    for j in range(width):
        power = width - 1 - j
        cells[:, 1 + j] = np.where(digits > power, _ZERO + (whole // 10**power) % 10, 0)
    cells[:, 1 + width] = _DOT
    for j in range(6):
        cells[:, 2 + width + j] = _ZERO + (frac // 10 ** (5 - j)) % 10
    slow = np.flatnonzero(~fast)
    if slow.size:
        cells = _python_formatted(cells, v, slow)
    return cells


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


def append_cells(rows: bytes, cells: list[np.ndarray]) -> bytes:
    """``rows`` (each ending in a newline) with ``,cell`` appended to each row for every matrix of
    ``cells`` (one row of bytes per text row, 0 where there is no byte), in order."""
    buf = np.frombuffer(rows, dtype=np.uint8)
    ends = np.flatnonzero(buf == _NEWLINE)
    n = len(ends)
    if n == 0:
        return rows
    comma = np.full((n, 1), _COMMA, dtype=np.uint8)
    parts = [m for block in cells for m in (comma, block)]
    tails = np.hstack([*parts, np.full((n, 1), _NEWLINE, dtype=np.uint8)])
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
    return out.tobytes()
