"""The grid over table behaviour: ramps, S-curves, ringing, measured/held/asynchronous references,
lost rows and their combinations. On every cell: every scheduled plateau is found (count and
rates), no row on a rate change is used, and the held-out error of the default model stays
within 1.3x of the same sensors (same seeds) recorded on an ideal table.

Figures: python tests/benchmarks/bench_table_grid.py
"""

import pytest
from support.trials.table_grid import GRID, ideal_rms, pooled_ratio, score_over_seeds


@pytest.fixture(scope="module")
def ideal():
    return ideal_rms()


@pytest.mark.parametrize(("name", "behaviour"), GRID, ids=[name for name, _ in GRID])
def test_grid_cell(ideal, name, behaviour):
    results = score_over_seeds(name, behaviour, ideal)
    for r in results:
        assert r.found == r.scheduled, f"{r.found} of {r.scheduled} plateaus"
        assert r.rates_ok, "a plateau's rate is off its scheduled rate"
        assert r.ramp_samples_used == 0
    assert pooled_ratio(results) <= 1.3
