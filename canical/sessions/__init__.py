"""A calibration session as data, and the files it is read from.

:class:`.session.Session` holds time, table rate, raw counts and auxiliary channels;
:mod:`.csv_file` reads and writes the CSV format (:mod:`.csv_chunks` reads it block by block,
:mod:`.row_means` reads a session too long to hold as means of consecutive samples,
:mod:`.fixed_cells` appends cells to rows held as bytes), :mod:`.canlog` decodes any CAN log
python-can reads (names of the formats in the light :mod:`.canlog_format`). Imports only
:mod:`canical.frames` and the ground floor.
"""

# The package's public face: the submodules (and names) other rings and the tests import;
# tests/test_rings.py keeps this list equal to those imports.
__all__ = [
    "canlog",
    "canlog_format",
    "csv_chunks",
    "csv_file",
    "fixed_cells",
    "reference_clock",
    "row_means",
    "session",
    "table_file",
    "triad_session",
]
