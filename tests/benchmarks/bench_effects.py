"""Closed loop over every simulated scenario: what was found, error before/after vs a told model.

All errors are rms on held-out plateaus (leave-plateaus-out, 2 s blocks), deg/s.
Run: python tests/benchmarks/bench_effects.py [seed]
"""

from __future__ import annotations

import sys
import time

from canical.evaluation import score_scenario
from canical.sim.scenarios import SCENARIOS


def main() -> None:
    seed = int(sys.argv[1]) if len(sys.argv) > 1 else 0
    print(f"{'scenario':54s} {'before':>8s} {'after':>8s} {'told':>8s} {'after/told':>10s}  ok  found")
    n_ok = 0
    t0 = time.perf_counter()
    for sc in SCENARIOS:
        r = score_scenario(sc, seed)
        n_ok += r.correct
        found = ", ".join(r.found) or "-"
        if r.confounded:
            found += "; confounded: " + " | ".join(" / ".join(g) for g in r.confounded)
        print(f"{sc.name[:54]:54s} {r.rms_before:8.4f} {r.rms_after:8.4f} {r.rms_oracle:8.4f} "
              f"{r.rms_after / r.rms_oracle:10.2f}  {'yes' if r.correct else 'NO '} {found}")
    print(f"\n{n_ok}/{len(SCENARIOS)} attributed as expected, seed {seed}, {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
