"""The cells of a CSV's rows parsed as numbers, and the first bad cell named when they are not.

Apart from :mod:`canical.sessions.csv_file` so that the whole-file reader and the block reader
(:mod:`canical.sessions.csv_chunks`) parse, and fail, alike.
"""

from __future__ import annotations

import csv
import io
import math

import numpy as np

from canical.errors import CanicalError


def parse_numeric(
    name: str, header: list[str], rows: list[str], first: int, usecols: list[int]
) -> dict[str, np.ndarray]:
    """Parse the chosen cells as floats with numpy's fast reader; on failure, find the bad cell."""
    if not usecols:
        return {}
    try:
        data = np.loadtxt(io.StringIO("\n".join(rows)), delimiter=",", ndmin=2, dtype=float, usecols=usecols)
    except (ValueError, IndexError):
        data = None
    if data is None or data.shape[0] != len(rows):
        _locate_bad_cell(name, header, rows, first, usecols)
        raise CanicalError(f"{name}: malformed CSV")  # pragma: no cover - locate raises
    finite = np.isfinite(data)
    if not finite.all():
        row, col = np.argwhere(~finite)[0]
        raise CanicalError(
            f"{name}: line {first + row}, column {header[usecols[col]]}: "
            f"value is not finite ({data[row, col]})"
        )
    return {header[c]: data[:, i] for i, c in enumerate(usecols)}


def _locate_bad_cell(name: str, header: list[str], rows: list[str], first: int, usecols: list[int]) -> None:
    """Walk the rows to name the first cell that is not a number."""
    for offset, cells in enumerate(csv.reader(rows)):
        if len(cells) != len(header):
            raise CanicalError(f"{name}: line {first + offset}: {len(cells)} cells, header has {len(header)}")
        for column, cell in ((header[c], cells[c]) for c in usecols):
            try:
                value = float(cell)
            except ValueError:
                raise CanicalError(
                    f"{name}: line {first + offset}, column {column}: {cell.strip()!r} is not a number"
                ) from None
            if not math.isfinite(value):
                raise CanicalError(
                    f"{name}: line {first + offset}, column {column}: value is not finite ({cell.strip()})"
                )
