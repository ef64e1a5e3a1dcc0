"""Every cell of the table grid through the bus flow: the emulated IMU on python-can's virtual
bus, `canical record` to a candump log, `canical calibrate` from it. Asserted per cell as on
the CSV grid (tests/trials/test_table_grid.py): every scheduled plateau found (count and rates) and
no used row on a rate change (by the table's truth); the held-out error within 1.3x of the
same sensor (same seed, same noise at the same plateau instants) on an ideal table through
the same flow, for every cell whose reference is the commanded rate.

Shorter than the CSV grid, stated: one seed (0), and 50 samples/s (the same 41 rates and 8 s
plateaus). A *measured* reference's jitter averages over half as many updates at 50 samples/s
and one seed's ratio is not pooled, so those cells' held-out ratio is measured and printed by
tests/benchmarks/bench_table_grid_bus.py, not asserted here (the CSV grid bounds them).
Real SocketCAN (vcan) runs a representative subset: tests/trials/test_table_bus.py.
"""

from pathlib import Path

import pytest

from canical.trials.table_grid import GRID, IDEAL
from canical.trials.table_grid_bus import bus_cell

SEED = 0


@pytest.fixture(scope="module")
def ideal(tmp_path_factory):
    r = bus_cell("ideal steps", IDEAL, tmp_path_factory.mktemp("ideal-bus"), seed=SEED)
    assert r.found == r.scheduled and r.rates_ok and r.ramp_samples_used == 0
    return r


@pytest.mark.parametrize(("name", "behaviour"), GRID[1:], ids=[name for name, _ in GRID[1:]])
def test_grid_cell_through_the_bus(ideal, name, behaviour, tmp_path: Path):
    r = bus_cell(name, behaviour, tmp_path, seed=SEED)
    assert r.found == r.scheduled, f"{r.found} of {r.scheduled} plateaus"
    assert r.rates_ok, "a plateau's rate is off its scheduled rate"
    assert r.ramp_samples_used == 0
    if behaviour.reference == "commanded":
        assert r.held_out_rms_dps <= 1.3 * ideal.held_out_rms_dps
