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

import functools

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
    groups = -(-len(str(int(whole.max(initial=0)))) // 3)
    # sign, the whole part's digits three at a time (right-aligned, 0 before the first shown
    # digit), the point, the fraction's six digits: each a field of the row, filled a field at
    # a time from the tables (a copy of 3-byte items, not a 2-D copy of 3-byte rows)
    fields = [("sign", "u1"), *((f"g{g}", "V3") for g in range(groups)), ("dot", "u1"), ("hi", "V3"),
              ("lo", "V3")]
    cells, rec = _record_rows(len(v), fields)
    rec["sign"] = np.where(np.signbit(v), _MINUS, 0)
    rest, lead = whole, None  # lead: every group before this one is 0
    for g in range(groups):
        power = 1000 ** (groups - 1 - g)
        part, rest = np.divmod(rest, power) if power > 1 else (rest, rest)
        shift = _UNITS if g == groups - 1 else _LEADING
        index = part + shift if lead is None else np.where(lead, part + shift, part)
        rec[f"g{g}"] = np.take(_GROUPS, index)
        lead = part == 0 if lead is None else lead & (part == 0)
    rec["dot"] = _DOT
    high, low = np.divmod(frac, 1000)
    rec["hi"] = np.take(_GROUPS, high)
    rec["lo"] = np.take(_GROUPS, low)
    slow = np.flatnonzero(~fast)
    if slow.size:
        cells = _python_formatted(cells, v, slow)
    return cells


def _groups_table() -> np.ndarray:
    """3-byte items: 0..999 as three digits ("007"); from :data:`_LEADING`, the same without the
    zeros before the first digit (0 as no byte at all: a leading group); from :data:`_UNITS`, the
    same with 0 shown (the units of a number with no group before them)."""
    table = np.zeros((3000, 3), dtype=np.uint8)
    table[:1000] = _DIGITS3
    for i in range(1000):
        text = str(i).encode("ascii")
        table[_UNITS + i, 3 - len(text):] = np.frombuffer(text, dtype=np.uint8)
        if i:
            table[_LEADING + i] = table[_UNITS + i]
    return table.view("V3").reshape(-1)


_LEADING, _UNITS = 1000, 2000
_GROUPS = _groups_table()


def _record_rows(n: int, fields: list[tuple[str, str]]) -> tuple[np.ndarray, np.ndarray]:
    """A matrix of ``n`` rows of bytes and the same memory seen as records of the named fields
    laid one after the other (filling a field is a copy of one item a row)."""
    dtype = np.dtype(fields)
    matrix = np.empty((n, dtype.itemsize), dtype=np.uint8)
    return matrix, matrix.view(dtype).reshape(n)


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
    dropped by one mask; a block with a row far longer than the rest (or a NUL byte, which the
    padded way reads as padding) takes the byte-offset way.
    """
    buf = np.frombuffer(rows, dtype=np.uint8)
    ends = np.flatnonzero(buf == _NEWLINE)
    n = len(ends)
    if n == 0:
        return memoryview(rows)
    starts = np.empty(n, dtype=np.int64)
    starts[0] = 0
    starts[1:] = ends[:-1] + 1
    lengths = ends - starts  # without the newline
    width = int(lengths.max())
    if (_PADDED_AT_MOST < 0 or width == 0 or n * (width + 1) > _PADDED_AT_MOST * len(buf) + 4096
            or b"\x00" in rows):
        comma = np.full((n, 1), _COMMA, dtype=np.uint8)
        parts = [m for block in cells for m in (comma, block)]
        tails = np.hstack([*parts, np.full((n, 1), _NEWLINE, dtype=np.uint8)])
        return _append_scattered(buf, ends, tails)
    return _append_padded(buf, starts, lengths, width, cells)


#: The padded matrix may hold this many times the block's bytes before the byte-offset way is used
#: (negative: always the byte-offset way, for tests).
_PADDED_AT_MOST = 3


def _append_padded(buf: np.ndarray, starts: np.ndarray, lengths: np.ndarray, width: int,
                   cells: list[np.ndarray]) -> memoryview:
    """Each row copied whole (a window of ``width`` bytes from its start) into a record beside its
    new cells; the bytes past the row's end cleared by a mask made for its length, and every
    0 byte (those, and the cells' absent bytes) dropped at once."""
    n = len(starts)
    fields: list[tuple[str, str]] = [("row", f"V{width}")]
    for k, matrix in enumerate(cells):
        fields += [(f"comma{k}", "u1"), *([(f"cell{k}", f"V{matrix.shape[1]}")] if matrix.shape[1] else [])]
    fields.append(("newline", "u1"))
    full, rec = _record_rows(n, fields)
    padded = np.zeros(len(buf) + width, dtype=np.uint8)  # every row's window lies inside
    padded[: len(buf)] = buf
    windows = np.ndarray((len(buf) + 1,), dtype=f"V{width}", buffer=padded, strides=(1,))
    rec["row"] = windows[starts]
    for k, matrix in enumerate(cells):
        rec[f"comma{k}"] = _COMMA
        if matrix.shape[1]:
            rec[f"cell{k}"] = np.ascontiguousarray(matrix, dtype=np.uint8).view(f"V{matrix.shape[1]}")[:, 0]
    rec["newline"] = _NEWLINE
    full &= np.take(_row_masks(width, full.shape[1]), lengths).view(np.uint8).reshape(full.shape)
    return full[full != 0].data


@functools.lru_cache(maxsize=8)
def _row_masks(width: int, total: int) -> np.ndarray:
    """Items of ``total`` bytes, one per row length L: 0xFF over the row's L bytes and the cells
    after the window, 0 over the rest of the window."""
    masks = np.full((width + 1, total), 0xFF, dtype=np.uint8)
    masks[:, :width][np.arange(width)[None, :] >= np.arange(width + 1)[:, None]] = 0
    return masks.view(f"V{total}").reshape(-1)


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
