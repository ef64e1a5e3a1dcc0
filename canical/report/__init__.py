"""What a calibration tells its user: the Markdown report and the plots.

:mod:`.markdown` writes report.md, :mod:`.plots` the residual, model and closed-loop figures,
:mod:`.allan_plot` the Allan deviation. Reads results of :mod:`canical.closed_loop` and
:mod:`canical.calibrate`; nothing below imports it.
"""

# The package's public face: the submodules (and names) other rings and the tests import;
# tests/test_rings.py keeps this list equal to those imports.
__all__ = [
    "allan_plot",
    "drive",
    "imu_report",
    "markdown",
    "plots",
]
