"""The proposed set's field term takes the field's line of standstill biases back to one value.

Why: the field measures the bias's temperature slope in deg/s at the standstills' own raw level
(b̄ + s·(T − T̄)), and a set's rate model is curved there; a single coefficient, the slope over
the model's gain at zero rate, left a cold vehicle's standstills up to 0.005 deg/s of the line
it had measured (daemon-z's model: 1 % of gain per deg/s near rest). The term is now fitted
where the evidence is (:func:`canical.fleet.proposal.field_shift`).
"""

from __future__ import annotations

import dataclasses
from pathlib import Path

import numpy as np
import pytest

from canical.fleet.proposal import Evidence, Level, with_field_term
from canical.sets import coefficient_file
from canical.sets.coefficients import CoefficientSet
from canical.sets.corrector import Corrector
from canical.sim.fleet_drives import raw_of

SET = Path(__file__).parents[1] / "data" / "sets" / "daemon-z.yaml"
TEMPS = np.linspace(-5.0, 45.0, 26)


def evidence(slope: float, level: Level) -> Evidence:
    return Evidence(slope, 4e-5, 250, 44, 1, 0.14, 0.003, level)


def spread_over_field(cset: CoefficientSet, slope: float, level: Level) -> float:
    """The largest minus the smallest output of ``cset`` at standstills on the field's line."""
    raw = raw_of(coefficient_file.load(SET), level.bias_dps + slope * (TEMPS - level.temp_c))
    out, _ = Corrector(cset).correct(raw, {"temp_c": TEMPS})
    return float(out.max() - out.min())


@pytest.mark.parametrize(("slope", "level"), [
    (0.028, Level(22.4, 13.1, -0.26)),   # cold climate: the bias crosses ±0.5 deg/s
    (-0.034, Level(20.0, 12.0, 0.30)),
    (-0.021, Level(38.0, 5.0, -0.50)),   # hot: far from rest all the time
])
def test_the_new_set_flattens_the_field_line_where_the_evidence_is(slope: float, level: Level) -> None:
    base = coefficient_file.load(SET)
    before = spread_over_field(base, slope, level)
    new, _ = with_field_term(base, evidence(slope, level), "fleet")
    after = spread_over_field(new, slope, level)
    assert before > 1.0  # the line spans a deg/s and more over -5..45 °C
    assert after < 1e-3 * before and after < 1e-3
    # the slope alone over the gain at rest (the proposal before) left 0.003 deg/s or more
    alone, _ = with_field_term(base, dataclasses.replace(evidence(slope, level), level=None), "fleet")
    assert spread_over_field(alone, slope, level) > 3 * after


def test_a_small_slope_gets_the_line_alone() -> None:
    """A curve worth less than 1e-4 deg/s over the span adds no square term."""
    new, _ = with_field_term(coefficient_file.load(SET), evidence(0.002, Level(25.0, 8.0, 0.05)), "fleet")
    assert [t.feature for t in new.terms] == ["offset"]
