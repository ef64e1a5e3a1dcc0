"""The table grid: calibration on sessions recorded the way real rate tables record them.

Each cell records the same simulated sensors (seeds 0-4) through one table behaviour (ramps,
S-curves, ringing, a measured/held/late/asynchronous reference, lost rows, combinations) on
the paper's protocol (-60..60 deg/s in 3 deg/s steps, 8 s plateaus, 100 samples/s) and
calibrates with the default model (closed loop off). Printed per cell: plateaus found of
scheduled (every seed), rows on a rate change that were used (the table's truth is known),
the reference noise and tolerance plateau finding estimated, and the held-out rms pooled
over seeds against the same sensors on an ideal table (instantaneous steps, commanded rate),
then each seed's own ratio: the sensor's noise is the same at the same instant of every
plateau on both tables (canical.sim.paired_noise), so a seed's ratio is a paired comparison.

Run: python tests/benchmarks/bench_table_grid.py [--quick]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from support.trials.table_grid import GRID, HARSH, ideal_rms, pooled_ratio, score_over_seeds


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes: checks the script runs")
    quick = parser.parse_args().quick
    start = time.perf_counter()
    ideal = ideal_rms(seeds=(0,)) if quick else ideal_rms()
    pooled_ideal = float(np.sqrt(np.mean(np.square(list(ideal.values())))))
    print(f"ideal table: held-out rms {pooled_ideal:.4f} deg/s pooled over seeds {sorted(ideal)}")
    header = (f"{'cell':58s} {'plateaus':>9s} {'ramp rows':>9s} {'rows used':>9s} {'ref noise':>9s} "
              f"{'tol':>6s} {'held-out':>8s} {'ratio':>5s}  per seed (paired: same sensor noise)")
    print(header)
    print("-" * len(header))
    sections = (("grid", GRID[:1]),) if quick else (("grid", GRID), ("beyond the grid", HARSH))
    for label, cells in sections:
        if label != "grid":
            print(f"-- {label}")
        for name, behaviour in cells:
            results = score_over_seeds(name, behaviour, ideal)
            found = min(r.found for r in results), max(r.found for r in results)
            found_text = f"{found[0]}" if found[0] == found[1] else f"{found[0]}-{found[1]}"
            ok = all(r.rates_ok for r in results)
            ratios = [r.ratio for r in results]
            pooled = float(np.sqrt(np.mean([r.held_out_rms_dps**2 for r in results])))
            print(f"{name[:58]:58s} {found_text:>5s}/{results[0].scheduled:<2d}{'' if ok else '!':1s} "
                  f"{sum(r.ramp_samples_used for r in results):9d} "
                  f"{np.mean([r.used / r.total for r in results]):9.0%} "
                  f"{np.mean([r.ref_noise_dps for r in results]):9.4f} "
                  f"{np.mean([r.rate_tol_dps for r in results]):6.3f} {pooled:8.4f} "
                  f"{pooled_ratio(results):5.2f}  {' '.join(f'{r:4.2f}' for r in ratios)}")
    print(f"({time.perf_counter() - start:.0f} s)")


if __name__ == "__main__":
    main()
