"""Read and write sessions as CSV: a header row, one row per sample.

Leading ``# key: value`` lines carry metadata (sensor id, axis). Columns
``time_s``, ``ref_dps`` and ``raw`` are the known ones (the latter two can be
renamed); every other column must be numeric and becomes an auxiliary channel.
Errors name the file, the line and the column, so the user can go and look.
"""

from __future__ import annotations

import csv
import io
import os
from collections.abc import Callable
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from canical.errors import CanicalError
from canical.sessions.csv_cells import parse_numeric
from canical.sessions.session import Session, parse_rail

TIME_COLUMN = "time_s"


@dataclass(frozen=True)
class CsvTable:
    """A CSV file as read: metadata, header, the original row texts and numeric columns."""

    path: str
    meta: dict[str, str]
    preamble: list[str]
    header: list[str]
    rows: list[str]
    columns: dict[str, np.ndarray]
    first_data_line: int


def read_table(path: str | os.PathLike[str], columns: list[str] | None = None) -> CsvTable:
    """Read a CSV file, keeping each row's text so it can be echoed unchanged.

    Only ``columns`` (all when ``None``) are parsed as numbers; the other cells
    are not looked at, so ``canical apply`` never reads a reference column.
    """
    name = str(path)
    try:
        text = Path(path).read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CanicalError(f"{name}: file not found") from None
    except UnicodeDecodeError as exc:
        raise CanicalError(f"{name}: not a text CSV file ({exc.reason})") from None
    except OSError as exc:
        raise CanicalError(f"{name}: cannot read ({exc.strerror})") from None
    lines = text.splitlines()
    meta: dict[str, str] = {}
    preamble: list[str] = []
    line_no = 0
    while line_no < len(lines) and (lines[line_no].startswith("#") or not lines[line_no].strip()):
        line = lines[line_no]
        preamble.append(line)
        if ":" in line:
            key, value = line.lstrip("#").split(":", 1)
            meta[key.strip()] = value.strip()
        line_no += 1
    if line_no >= len(lines):
        raise CanicalError(f"{name}: empty file (no header row)")
    header = [cell.strip() for cell in next(csv.reader([lines[line_no]]))]
    if len(set(header)) != len(header):
        dupes = sorted({h for h in header if header.count(h) > 1})
        raise CanicalError(f"{name}: duplicate column name(s) {', '.join(dupes)}")
    rows = [line for line in lines[line_no + 1 :] if line.strip()]
    if not rows:
        raise CanicalError(f"{name}: no data rows after the header")
    first = line_no + 2
    wanted = header if columns is None else columns
    for column in wanted:
        if column not in header:
            raise CanicalError(f"{name}: missing column {column!r} (columns: {', '.join(header)})")
    parsed = parse_numeric(name, header, rows, first, [header.index(c) for c in wanted])
    return CsvTable(name, meta, preamble, header, rows, parsed, first)


def session_from_table(
    table: CsvTable,
    *,
    raw_column: str = "raw",
    ref_column: str | None = "ref_dps",
    settled_column: str | None = None,
) -> Session:
    """Pick the session's columns out of a table; ``ref_column=None`` means field data.

    ``settled_column`` names the table's settled flag (nonzero: settled); it is kept apart
    from the auxiliary channels.
    """
    needed = [c for c in (raw_column, ref_column, settled_column) if c]
    for column in needed:
        if column not in table.columns:
            have = ", ".join(table.header)
            raise CanicalError(f"{table.path}: missing column {column!r} (columns: {have})")
    time_s = table.columns.get(TIME_COLUMN)
    if time_s is None:
        raise CanicalError(f"{table.path}: missing column {TIME_COLUMN!r}")
    n = len(time_s)
    if n > 1 and np.any(np.diff(time_s) < 0):
        bad = int(np.argmax(np.diff(time_s) < 0)) + 1
        raise CanicalError(f"{table.path}: line {table.first_data_line + bad}: time_s goes backwards")
    rail = parse_rail(table.meta["rail"], f"{table.path}: # rail") if "rail" in table.meta else None
    known = {TIME_COLUMN, raw_column, ref_column or "ref_dps", settled_column}
    aux = {c: v for c, v in table.columns.items() if c not in known}
    return Session(
        time_s=time_s,
        raw=table.columns[raw_column],
        ref_dps=table.columns[ref_column] if ref_column else None,
        aux=aux,
        meta=dict(table.meta),
        settled=table.columns[settled_column] != 0 if settled_column else None,
        rail=rail,
    )


def read_session(
    path: str | os.PathLike[str],
    *,
    raw_column: str = "raw",
    ref_column: str | None = "ref_dps",
    settled_column: str | None = None,
    on_block: Callable[[int], None] | None = None,
    max_rows: int | None = None,
) -> Session:
    """Read a session CSV file (its columns only, block by block: no row text is kept);
    ``on_block`` hears the bytes read so far.

    A session longer than ``max_rows`` rows (default
    :data:`~canical.sessions.row_means.REDUCE_ABOVE_ROWS`) is read as means of consecutive
    samples (:mod:`canical.sessions.row_means`; ``Session.means`` says how); a shorter one is
    read as it is.
    """
    from canical.sessions.csv_chunks import read_columns  # they read their head with this module
    from canical.sessions.row_means import read_row_means

    reduced = read_row_means(path, raw_column=raw_column, settled_column=settled_column,
                             max_rows=max_rows, on_block=on_block)
    table, means = reduced if reduced is not None else (read_columns(path, on_block=on_block), None)
    session = session_from_table(table, raw_column=raw_column, ref_column=ref_column,
                                 settled_column=settled_column)
    return session if means is None else replace(session, means=means)


def format_session(session: Session, *, float_format: str = "%.9g") -> str:
    """A session as CSV text, metadata first, in the format :func:`read_session` reads."""
    out = io.StringIO()
    for key, value in session.meta.items():
        out.write(f"# {key}: {value}\n")
    if session.rail is not None and "rail" not in session.meta:
        out.write(f"# rail: {session.rail.low!r},{session.rail.high!r}\n")
    names = [TIME_COLUMN]
    cols = [session.time_s]
    if session.ref_dps is not None:
        names.append("ref_dps")
        cols.append(session.ref_dps)
    names.append("raw")
    cols.append(session.raw)
    if session.settled is not None:
        names.append("settled")
        cols.append(session.settled.astype(float))
    for name, values in session.aux.items():
        names.append(name)
        cols.append(values)
    out.write(",".join(names) + "\n")
    np.savetxt(out, np.column_stack(cols), delimiter=",", fmt=float_format)
    return out.getvalue()
