"""Trials of the whole pipeline on awkward simulated equipment.

:mod:`.table_grid` runs calibration on a grid of table recording styles (ramps, ringing,
measured, held, late or asynchronous references, lost rows) against an ideal table;
:mod:`.table_grid_bus` runs the same grid through the bus flow (emulate, record, calibrate).
Used by tests and benchmarks; the top ring beside :mod:`canical.commands`.
"""

# The package's public face: the submodules (and names) other rings and the tests import;
# tests/test_rings.py keeps this list equal to those imports.
__all__ = [
    "table_grid",
    "table_grid_bus",
]
