"""Closed loop over every simulated scenario: what was found, error before/after vs a told model.

All errors are rms on held-out plateaus (leave-plateaus-out, 2 s blocks), deg/s.
``told`` is the same loop's structure given the true effect's term forms; ``left``
is the residual after the loop over the session's noise floor (flagged ``!`` when
the report calls it unexplained). The last line is a sensor whose error follows a
variable nobody recorded: no candidate can represent it, and it must be flagged.
Run: python tests/benchmarks/bench_effects.py [seed]
"""

from __future__ import annotations

import sys
import time

from canical.evaluation import score_scenario
from canical.sim.scenarios import SCENARIOS, UNEXPLAINED


def main() -> None:
    seed = int(sys.argv[1]) if len(sys.argv) > 1 else 0
    head = f"{'before':>7s} {'after':>7s} {'told':>7s} {'a/told':>6s} {'left':>6s}"
    print(f"{'scenario':58s} {head}  ok  found")
    n_ok = 0
    t0 = time.perf_counter()
    for sc in (*SCENARIOS, UNEXPLAINED):
        r = score_scenario(sc, seed)
        n_ok += r.correct
        found = ", ".join(r.found) or "-"
        if r.confounded:
            found += "; confounded: " + " | ".join(" / ".join(g) for g in r.confounded)
        left = f"{r.unexplained_ratio:5.1f}{'!' if r.unexplained else ' '}"
        ok = "yes" if r.correct else "NO "
        print(f"{sc.name[:58]:58s} {r.rms_before:7.4f} {r.rms_after:7.4f} {r.rms_oracle:7.4f} "
              f"{r.rms_after / r.rms_oracle:6.2f} {left}  {ok} {found}", flush=True)
    seconds = time.perf_counter() - t0
    print(f"\n{n_ok}/{len(SCENARIOS) + 1} attributed as expected, seed {seed}, {seconds:.0f} s")


if __name__ == "__main__":
    main()
