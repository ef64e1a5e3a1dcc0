"""Read a CSV file block by block: its head once, then its rows a few megabytes at a time.

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

#: Bytes read per block: some 200,000 rows of a three-column session.
CHUNK_BYTES = 4 << 20
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
                 on_block: Callable[[int], None] | None = None) -> CsvTable:
    """``read_table`` without the rows' text (``rows`` is empty): the columns parsed block by
    block, so memory holds the numbers, not the file. ``on_block`` hears the bytes read so far."""
    head = read_head(path)
    if head is None:
        table = read_table(path, columns)
        return CsvTable(table.path, table.meta, table.preamble, table.header, [], table.columns,
                        table.first_data_line)
    wanted = head.header if columns is None else columns
    parts: list[dict[str, np.ndarray]] = []
    done = head.data_offset
    for chunk in read_chunks(head, wanted):
        parts.append(chunk.columns)
        done += chunk.size
        if on_block is not None:
            on_block(done)
    parsed = {}
    for name in dict.fromkeys(wanted):  # one column at a time: the blocks' copies go as it is made
        parsed[name] = np.concatenate([p.pop(name) for p in parts])
    return CsvTable(head.path, head.meta, head.preamble, head.header, [], parsed, head.first_data_line)


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
    if _is_plain(block, buf, n_rows) and (usecols or not _has_blank_row(block, buf)):
        columns = _parse_plain(head, block, usecols, n_rows)
        if columns is not None:
            return CsvChunk(first_row, n_rows, len(block), columns, text=block)
    text = _decode(head.path, block)
    rows = [line for line in text.splitlines() if line.strip()]
    columns = parse_numeric(head.path, head.header, rows, head.first_data_line + first_row, usecols)
    return CsvChunk(first_row, len(rows), len(block), columns, rows=rows)


def _is_plain(block: bytes, buf: np.ndarray, newlines: int) -> bool:
    """Whether every byte is a tab, a newline or space..tilde (what a plain block may hold),
    without looking each byte up: ASCII below DEL, its only bytes below a space its newlines
    and tabs."""
    if not (block.isascii() and int(buf.max(initial=0)) < 127):
        return False
    tabs = block.count(b"\t") if b"\t" in block else 0
    return int(np.count_nonzero(buf < 32)) == newlines + tabs


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
    # Each column its own array, so that a column gathered from the blocks frees theirs.
    return {head.header[c]: np.ascontiguousarray(data[:, i]) for i, c in enumerate(usecols)}


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
