"""Read a CSV file block by block: its head once, then its rows a quarter of a megabyte at a time.

Why: :func:`canical.sessions.csv_file.read_table` holds the whole file, every row as a string
and every column parsed, about 280 bytes per row; a session of hours at 1 kHz does not fit.
Here memory is bounded by the block. Rows, metadata, header and errors are exactly those of
``read_table`` (the same lines kept, the same numbers parsed by the same call, the same
messages naming the same lines): a block of plain ASCII rows split on newlines stays bytes;
a block with anything else (a carriage return, a blank row, a non-ASCII byte) is split as
``read_table`` splits text, row by row.
"""

from __future__ import annotations

import csv
import importlib
import io
import os
from collections.abc import Callable, Iterator
from dataclasses import dataclass
from typing import BinaryIO

import numpy as np

from canical.errors import CanicalError
from canical.sessions.csv_cells import parse_numeric
from canical.sessions.csv_file import CsvTable, read_table

#: Bytes read per block: some 14,000 rows of a three-column session. Small enough that a block's
#: temporaries stay in the processor's cache and the allocator reuses them from block to block
#: (blocks of megabytes spend as long again in the kernel, mapping fresh pages).
CHUNK_BYTES = 256 << 10
_NEWLINE = 10


def _file_reader() -> Callable[..., np.ndarray] | None:
    """numpy's own reader under ``loadtxt``, or None where this numpy has no such function."""
    try:
        module = importlib.import_module("numpy._core._multiarray_umath")
    except ImportError:
        return None
    reader = getattr(module, "_load_from_filelike", None)
    return reader if callable(reader) else None


#: ``loadtxt`` reads a file it opens from its path a large block at a time, but anything else
#: (a buffer of bytes among them) a line at a time, a third slower. The same C reader is handed
#: the block as a file here; where it is missing or takes other arguments (another numpy),
#: ``loadtxt`` itself (set to None after the first refusal).
_READ_FILE = _file_reader()


@dataclass(frozen=True)
class CsvHead:
    """What precedes the rows: metadata lines, the header, where the rows begin."""

    path: str
    meta: dict[str, str]
    preamble: list[str]
    header: list[str]
    first_data_line: int  # line number of the first row, as read_table counts
    data_offset: int  # byte offset of the line after the header


@dataclass(frozen=True)
class CsvChunk:
    """A block of rows and the chosen columns parsed.

    ``text`` holds the rows as read, each ending in a newline, when the block is plain;
    otherwise ``rows`` holds them as ``read_table`` keeps them (one string per row, no newline).
    """

    first_row: int  # index of the block's first row among the file's rows
    n_rows: int
    size: int  # bytes of the file the block spans
    columns: dict[str, np.ndarray]
    text: bytes | None = None
    rows: list[str] | None = None


def read_head(path: str | os.PathLike[str]) -> CsvHead | None:
    """The file's head as ``read_table`` reads it; None when a line of it holds a line break
    ``str.splitlines`` knows other than a newline or a carriage return and newline (a lone
    carriage return, a form feed...): such a file is left to ``read_table``."""
    name = str(path)
    meta: dict[str, str] = {}
    preamble: list[str] = []
    offset = 0
    with _open(name) as f:
        for line_no, raw_line in enumerate(iter(f.readline, b"")):
            offset += len(raw_line)
            line = _decode(name, raw_line.removesuffix(b"\n").removesuffix(b"\r"))
            if len(f"{line}.".splitlines()) > 1:  # a break splitlines knows, "\r" among them
                return None
            if line.startswith("#") or not line.strip():
                preamble.append(line)
                if ":" in line:
                    key, value = line.lstrip("#").split(":", 1)
                    meta[key.strip()] = value.strip()
                continue
            header = [cell.strip() for cell in next(csv.reader([line]))]
            if len(set(header)) != len(header):
                dupes = sorted({h for h in header if header.count(h) > 1})
                raise CanicalError(f"{name}: duplicate column name(s) {', '.join(dupes)}")
            return CsvHead(name, meta, preamble, header, line_no + 2, offset)
    raise CanicalError(f"{name}: empty file (no header row)")


def read_chunks(head: CsvHead, columns: list[str], chunk_bytes: int | None = None) -> Iterator[CsvChunk]:
    """The rows after ``head``, block by block, with ``columns`` parsed as ``read_table`` parses
    them; the errors of ``read_table`` (a missing column, no rows, a bad cell) as they are met."""
    chunk_bytes = chunk_bytes or CHUNK_BYTES
    first_row = 0
    with _open(head.path) as f:
        f.seek(head.data_offset)
        if not any(_decode(head.path, block).strip() for block in _blocks(f, chunk_bytes)):
            raise CanicalError(f"{head.path}: no data rows after the header")
        usecols = [_column_index(head, c) for c in columns]
        f.seek(head.data_offset)
        for block in _blocks(f, chunk_bytes):
            chunk = _chunk(head, block, usecols, first_row)
            if chunk.n_rows:
                first_row += chunk.n_rows
                yield chunk


def read_columns(path: str | os.PathLike[str], columns: list[str] | None = None,
                 on_block: Callable[[int], None] | None = None,
                 convert: Callable[[dict[str, np.ndarray]], dict[str, np.ndarray]] | None = None) -> CsvTable:
    """``read_table`` without the rows' text (``rows`` is empty): the columns parsed block by
    block, so memory holds the numbers, not the file. ``on_block`` hears the bytes read so far.

    ``convert``, when given, maps each block's columns (in row order, block after block) to the
    columns kept, so that a column needed only to derive another (the raw counts of a rate) is
    never held whole; the file read whole (a head only ``read_table`` reads) goes through it
    as one block.
    """
    head = read_head(path)
    if head is None:
        table = read_table(path, columns)
        kept = convert(table.columns) if convert is not None else table.columns
        return CsvTable(table.path, table.meta, table.preamble, table.header, [], kept,
                        table.first_data_line)
    wanted = list(dict.fromkeys(head.header if columns is None else columns))
    # Each block's numbers go straight into columns sized for the file (from the first block's
    # bytes per row, enlarged if later rows are shorter; pages past the rows are never
    # written): no block is kept until the end and no column is joined from copies.
    parsed: dict[str, np.ndarray] = {}
    filled = 0
    done = head.data_offset
    rest = os.path.getsize(head.path) - head.data_offset
    for chunk in read_chunks(head, wanted):
        block = convert(chunk.columns) if convert is not None else chunk.columns
        if not parsed:
            size = chunk.n_rows + -(-chunk.n_rows * max(rest - chunk.size, 0) * 21 // (chunk.size * 20))
            parsed = {name: np.empty(size) for name in block}
        elif filled + chunk.n_rows > len(next(iter(parsed.values()))):
            grown = max(filled + chunk.n_rows, len(next(iter(parsed.values()))) * 5 // 4)
            parsed = {name: _enlarged(values, filled, grown) for name, values in parsed.items()}
        for name, values in block.items():
            parsed[name][filled : filled + chunk.n_rows] = values
        filled += chunk.n_rows
        done += chunk.size
        if on_block is not None:
            on_block(done)
    kept = {name: values[:filled] for name, values in parsed.items()}
    return CsvTable(head.path, head.meta, head.preamble, head.header, [], kept, head.first_data_line)


def _enlarged(values: np.ndarray, filled: int, size: int) -> np.ndarray:
    out = np.empty(size)
    out[:filled] = values[:filled]
    return out


def count_lines(head: CsvHead) -> int:
    """Lines after the header (blank ones too), counted a block at a time without parsing."""
    lines, last = 0, b"\n"
    with _open(head.path) as f:
        f.seek(head.data_offset)
        while block := f.read(CHUNK_BYTES):
            lines += block.count(b"\n")
            last = block[-1:]
    return lines + (last != b"\n")


def read_header(path: str | os.PathLike[str]) -> list[str]:
    """The header's column names, reading no further than the head when it can."""
    head = read_head(path)
    return head.header if head is not None else read_table(path, columns=[]).header


def check_columns(head: CsvHead, columns: list[str]) -> None:
    """Every one of ``columns`` is in the header (read_table's message otherwise)."""
    for column in columns:
        _column_index(head, column)


def _column_index(head: CsvHead, column: str) -> int:
    if column not in head.header:
        raise CanicalError(f"{head.path}: missing column {column!r} (columns: {', '.join(head.header)})")
    return head.header.index(column)


def _open(name: str) -> BinaryIO:
    try:
        return open(name, "rb")
    except FileNotFoundError:
        raise CanicalError(f"{name}: file not found") from None
    except OSError as exc:
        raise CanicalError(f"{name}: cannot read ({exc.strerror})") from None


def _decode(name: str, data: bytes) -> str:
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise CanicalError(f"{name}: not a text CSV file ({exc.reason})") from None


def _blocks(f: BinaryIO, chunk_bytes: int) -> Iterator[bytes]:
    """Whole lines, each ending in a newline (one added to a last line without)."""
    rest = b""
    while True:
        data = f.read(chunk_bytes)
        if not data:
            break
        data = rest + data
        cut = data.rfind(b"\n") + 1
        rest = data[cut:]
        if cut:
            yield data[:cut]
    if rest:
        yield rest + b"\n"


def _chunk(head: CsvHead, block: bytes, usecols: list[int], first_row: int) -> CsvChunk:
    """A block as bytes when its rows are plain lines and its cells parse at once; else as rows.

    A blank row (which read_table drops) needs no search first when columns are parsed: numpy's
    reader skips an empty line (one row fewer than the newlines) and refuses one of spaces, and
    either sends the block to the rows.
    """
    buf = np.frombuffer(block, dtype=np.uint8)
    n_rows = block.count(b"\n")
    if _is_plain(block) and (usecols or not _has_blank_row(block, buf)):
        columns = _parse_plain(head, block, usecols, n_rows)
        if columns is not None:
            return CsvChunk(first_row, n_rows, len(block), columns, text=block)
    text = _decode(head.path, block)
    rows = [line for line in text.splitlines() if line.strip()]
    columns = parse_numeric(head.path, head.header, rows, head.first_data_line + first_row, usecols)
    return CsvChunk(first_row, len(rows), len(block), columns, rows=rows)


#: The bytes a plain block may hold: tab, newline, space..tilde.
_PLAIN_BYTES = b"\t\n" + bytes(range(32, 127))


def _is_plain(block: bytes) -> bool:
    """Whether every byte is a tab, a newline or space..tilde (what a plain block may hold): the
    block with those deleted is empty (one pass in C, no array of comparisons)."""
    return not block.translate(None, _PLAIN_BYTES)


def _has_blank_row(block: bytes, buf: np.ndarray) -> bool:
    """Whether a plain block has a row of nothing but spaces and tabs (read_table drops those).

    Such a row starts with a space, a tab or its newline: when no row does, there is none.
    (A space or tab found at all first: a numeric block seldom has one, and looking for one
    byte is far quicker than for two.)
    """
    if not (block.startswith((b" ", b"\t", b"\n")) or b"\n\n" in block
            or (b" " in block and b"\n " in block) or (b"\t" in block and b"\n\t" in block)):
        return False
    ends = np.flatnonzero(buf == _NEWLINE)
    starts = np.concatenate([[0], ends[:-1] + 1])
    filled = np.concatenate([[0], np.cumsum((buf != 32) & (buf != 9) & (buf != _NEWLINE))])
    return bool((filled[ends] == filled[starts]).any())


def _parse_plain(head: CsvHead, block: bytes, usecols: list[int],
                 n_rows: int) -> dict[str, np.ndarray] | None:
    """The columns of a plain block, or None when any cell needs read_table's row-by-row look."""
    if not usecols:
        return {}
    try:
        data = _loadtxt(block, usecols)
    except (ValueError, IndexError):
        return None
    if data.shape[0] != n_rows or not np.isfinite(data).all():
        return None
    # Views of the block's rows: a reader copies them where it keeps them (into its columns, or
    # reduced to means), so no copy is made here.
    return {head.header[c]: data[:, i] for i, c in enumerate(usecols)}


def _loadtxt(block: bytes, usecols: list[int]) -> np.ndarray:
    """``np.loadtxt(io.BytesIO(block), delimiter=",", ndmin=2, dtype=float, usecols=usecols)``:
    the same reader with the same settings (loadtxt's defaults: ``#`` comments, no quotes), the
    block read as a file."""
    global _READ_FILE
    if _READ_FILE is not None:
        try:
            data = _READ_FILE(io.BytesIO(block), delimiter=",", comment="#", quote=None, imaginary_unit="j",
                              usecols=usecols, skiplines=0, max_rows=-1, converters=None,
                              dtype=np.dtype(float), encoding="latin1", filelike=True, byte_converters=False)
        except TypeError:  # another numpy's arguments
            _READ_FILE = None
        else:
            return data.reshape(-1, len(usecols))
    return np.loadtxt(io.BytesIO(block), delimiter=",", ndmin=2, dtype=float, usecols=usecols)
