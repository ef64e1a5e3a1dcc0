"""The Allan deviation canical computes equals Stable32's published table on a real record.

allantools ships, in its source distribution, a 10 MHz OCXO's frequency record (19,982 s at
1 Hz) with Stable32's overlapping Allan deviation at every averaging factor. canical's curve
(:func:`canical.calibrate.allan.allan_deviation`: its τ grid, its pooling) must give the same
σ at every τ both have, to the five digits Stable32 prints.
"""

from __future__ import annotations

import allantools
import numpy as np
import pytest
from support.sdist_files import sdist_files

from canical.calibrate.allan import allan_deviation

FILES = ("tests/ocxo/ocxo_frequency.txt", "tests/ocxo/stable32_oadev_alltau.txt")


def test_the_curve_equals_stable32_on_an_ocxo_record() -> None:
    folder = sdist_files("allantools", allantools.__version__, FILES)
    freq = np.loadtxt(folder / "tests__ocxo__ocxo_frequency.txt", comments="#")
    table = np.loadtxt(folder / "tests__ocxo__stable32_oadev_alltau.txt", comments="#")
    stable32 = {int(row[0]): row[5] for row in table}
    curve = allan_deviation([(freq - 1e7) / 1e7], 1.0)  # fractional frequency, 1 Hz
    compared = 0
    for m, sigma in zip(np.round(curve.tau_s).astype(int), curve.adev, strict=True):
        if m in stable32:
            assert sigma == pytest.approx(stable32[m], rel=1e-4), m
            compared += 1
    assert compared >= 12  # one to a few thousand seconds, on canical's own τ grid
