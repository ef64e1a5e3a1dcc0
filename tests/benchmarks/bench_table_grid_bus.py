"""The table grid through the bus flow: emulated IMU -> canical record -> canical calibrate.

Every cell of the CSV grid (bench_table_grid.py) played by the emulated IMU on python-can's
virtual bus, recorded to a candump log and calibrated from it, on a shorter programme than
the CSV grid's (-60..60 deg/s in 3 deg/s steps and 8 s plateaus as there, but 50 samples/s; see
support.trials.table_grid_bus). Printed per cell: plateaus found of scheduled, rows on a rate
change that were used (the table's truth is known), raw frames recorded, the held-out rms
pooled over seeds and its ratio to the same sensors (same seeds, same noise at the same
plateau instants) on an ideal table through the same flow, the per-seed ratios, and the same
ratio for the very same emulated passes calibrated without the bus (the emulator's samples as
a session: support.trials.table_grid_bus.stream_session), so the bus's own cost is the
difference of the last two columns.

Run: python tests/benchmarks/bench_table_grid_bus.py [SEEDS, default 0,1,2,3,4] [--quick]
(``--quick``: seed 0, the ideal table and the grid's first cell; checks that the script runs.)
"""

from __future__ import annotations

import argparse
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from support.trials.table_grid import GRID, IDEAL
from support.trials.table_grid_bus import bus_cell, pooled_bus_ratio, stream_held_out_rms


def main(seeds: tuple[int, ...], cells: int | None = None) -> None:
    start = time.perf_counter()
    with tempfile.TemporaryDirectory(prefix="bench-grid-bus-") as tmp:
        folder = Path(tmp)
        ideal = {s: bus_cell("ideal steps", IDEAL, folder / f"ideal-{s}", seed=s) for s in seeds}
        print("ideal table through the bus: held-out rms "
              + ", ".join(f"seed {s} {r.held_out_rms_dps:.4f}" for s, r in ideal.items()) + " deg/s")
        no_bus_ideal = {s: stream_held_out_rms(IDEAL, seed=s) for s in seeds}
        header = (f"{'cell':58s} {'plateaus':>9s} {'ramp rows':>9s} {'frames':>7s} {'held-out':>8s} "
                  f"{'ratio':>5s}  {'per seed':{5 * len(seeds)}s} {'same passes, no bus':>19s}")
        print(header)
        print("-" * len(header))
        for i, (name, behaviour) in enumerate(GRID[:cells]):
            results = [bus_cell(name, behaviour, folder / f"{i}-{s}", seed=s) for s in seeds]
            found = {r.found for r in results}
            found_text = "/".join(str(f) for f in sorted(found))
            ok = all(r.rates_ok for r in results)
            pooled = float(np.sqrt(np.mean([r.held_out_rms_dps**2 for r in results])))
            per_seed = " ".join(f"{r.held_out_rms_dps / ideal[r.seed].held_out_rms_dps:4.2f}"
                                for r in results)
            no_bus = [stream_held_out_rms(behaviour, seed=s) for s in seeds]
            no_bus_ratio = float(np.sqrt(np.mean(np.square(no_bus))
                                         / np.mean(np.square([no_bus_ideal[s] for s in seeds]))))
            print(f"{name[:58]:58s} {found_text:>5s}/{results[0].scheduled:<2d}{'' if ok else '!':1s} "
                  f"{sum(r.ramp_samples_used for r in results):9d} "
                  f"{int(np.mean([r.frames for r in results])):7d} "
                  f"{pooled:8.4f} {pooled_bus_ratio(results, ideal):5.2f}  {per_seed:{5 * len(seeds)}s} "
                  f"{no_bus_ratio:19.2f}",
                  flush=True)
    print(f"({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("seeds", nargs="?", default="0,1,2,3,4", help="comma-separated seeds")
    parser.add_argument("--quick", action="store_true", help="small sizes: checks the script runs")
    args = parser.parse_args()
    if args.quick:
        main((0,), cells=1)
    else:
        main(tuple(int(s) for s in args.seeds.split(",")))
