"""Closed loop over every simulated scenario: what was found, error before/after vs a told model.

All errors are rms on held-out plateaus (leave-plateaus-out, 2 s blocks), deg/s.
``told`` is the same loop's structure given the true effect's term forms; ``left``
is the residual after the loop over the session's noise floor (flagged ``!`` when
the report calls it unexplained). The last line is a sensor whose error follows a
variable nobody recorded: no candidate can represent it, and it must be flagged.
With several seeds, a seed × scenario table of the verdicts follows (``yes``: as
expected; otherwise what was found, ``C`` for a reported confound), and for every
reported confound the paired p-values that decided it.

Run: python tests/benchmarks/bench_effects.py [SEED ...] [--only TEXT] [--dwell S] [--quick]
(``--only`` keeps scenarios whose name contains TEXT; repeat it for several.)
"""

from __future__ import annotations

import argparse
import time

from canical.evaluation import score_scenario
from canical.sim.scenarios import SCENARIOS, UNEXPLAINED


def verdict(r) -> str:
    """One short cell: yes, or what the loop did instead."""
    if r.correct:
        return "yes"
    found = "+".join(r.found) or "-"
    return f"NO {found}{' C' if r.confounded else ''}"


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("seeds", nargs="*", type=int, default=[0])
    parser.add_argument("--only", action="append", default=[])
    parser.add_argument("--dwell", type=float, default=10.0)
    parser.add_argument("--quick", action="store_true", help="small sizes: checks the script runs")
    args = parser.parse_args()
    scenarios = [sc for sc in (*SCENARIOS, UNEXPLAINED)
                 if not args.only or any(o in sc.name for o in args.only)]
    if args.quick:
        args.seeds, scenarios = args.seeds[:1], scenarios[:1]
    head = f"{'before':>7s} {'after':>7s} {'told':>7s} {'a/told':>6s} {'left':>6s}"
    table: dict[str, list[str]] = {sc.name: [] for sc in scenarios}
    decisions: list[str] = []
    for seed in args.seeds:
        print(f"seed {seed}, dwell {args.dwell:g} s\n{'scenario':58s} {head}  ok  found")
        n_ok = 0
        t0 = time.perf_counter()
        for sc in scenarios:
            r = score_scenario(sc, seed, args.dwell)
            n_ok += r.correct
            table[sc.name].append(verdict(r))
            found = ", ".join(r.found) or "-"
            if r.confounded:
                found += "; confounded: " + " | ".join(" / ".join(g) for g in r.confounded)
            for group in r.paired_p:
                decisions.append(f"  seed {seed} {sc.name[:40]}: " + ", ".join(
                    f"{name} p={p:.2g}" for name, p in group.items()))
            left = f"{r.unexplained_ratio:5.1f}{'!' if r.unexplained else ' '}"
            ok = "yes" if r.correct else "NO "
            print(f"{sc.name[:58]:58s} {r.rms_before:7.4f} {r.rms_after:7.4f} {r.rms_oracle:7.4f} "
                  f"{r.rms_after / r.rms_oracle:6.2f} {left}  {ok} {found}", flush=True)
        seconds = time.perf_counter() - t0
        print(f"\n{n_ok}/{len(scenarios)} attributed as expected, seed {seed}, {seconds:.0f} s\n", flush=True)
    if len(args.seeds) > 1:
        print(f"{'scenario':58s} " + " ".join(f"{'seed ' + str(s):>9s}" for s in args.seeds))
        for name, cells in table.items():
            print(f"{name[:58]:58s} " + " ".join(f"{c:>9s}" for c in cells))
    if decisions:
        print("\nreported confounds: one-sided paired p that the first named predicts held-out plateaus "
              "better than each other one (confounded when every p >= the level, 0.01)")
        print("\n".join(decisions))


if __name__ == "__main__":
    main()
