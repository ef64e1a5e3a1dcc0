"""Raw drives of a simulated fleet's vehicles, for ``fleet replay`` (``simulate fleet --drives``).

Why from the fleet's truth: a replay judges a proposed set against the same sensor the field log
came from, so each vehicle's drive has its sensor's temperature slope left over by the set, its
turn-on bias mean and spread, and its climate's cabin start (:mod:`canical.sim.drive` makes the
drive: stops, turns, creep, power cycles, the cabin warming). Why raw: the sets under test act on
the raw output, so the rate the table calibration gives is turned back into raw units through
the baseline set's own rate model (its inverse, by interpolation on a fine grid).
"""

from __future__ import annotations

import numpy as np

from canical.models.piecewise import PiecewisePoly
from canical.sets.coefficients import CoefficientSet
from canical.sim.drive import Drive, DriveModel, simulate_drive
from canical.sim.fleet import CLIMATES, REFERENCE_C, SensorTruth

#: The columns a simulated raw drive's CSV has, in order.
COLUMNS = ("time_s", "raw", "temp_c", "speed_mps", "true_rate_dps")


def drive_for(truth: SensorTruth, index: int, number: int, seed: int = 0) -> Drive:
    """Vehicle ``index``'s drive ``number``: its sensor's slope, turn-on bias and climate."""
    model = DriveModel(first_turn_on_dps=truth.turn_on_mean_dps, turn_on_spread_dps=truth.turn_on_spread_dps,
                       temp_slope_dps_per_c=truth.slope_dps_per_c,
                       cabin_start_c=CLIMATES[truth.climate][0], cabin_end_c=45.0, cabin_tau_s=400.0,
                       slope_reference_c=REFERENCE_C)
    rng = np.random.default_rng([seed, index, number, 7])
    return simulate_drive(int(rng.integers(2**31)), model)


def raw_of(cset: CoefficientSet, rate_dps: np.ndarray) -> np.ndarray:
    """The raw output the set turns into ``rate_dps`` (its rate model inverted; no terms)."""
    model = cset.rate_model()
    if not isinstance(model, PiecewisePoly) or cset.terms:
        raise ValueError("a segmented set without effect terms")
    lo, hi = cset.span_raw
    grid = np.linspace(lo - cset.v0, hi - cset.v0, 200_001)
    rates, _ = model.evaluate(grid)
    if not np.all(np.diff(rates) > 0):
        raise ValueError("a rate model that rises over its span")
    out: np.ndarray = cset.v0 + np.interp(rate_dps, rates, grid)
    return out
