"""Closed loop over every simulated scenario, on several seeds: what was found, and the error
before and after against a told model, with its spread over the seeds.

All errors are rms on held-out plateaus (leave-plateaus-out, 2 s blocks), deg/s.
``told`` is the same loop's structure given the true effect's term forms; ``left``
is the residual after the loop over the session's noise floor (flagged ``!`` when
the report calls it unexplained). The scenarios are the enumerated effects, the smooth
effects (``SMOOTH_SCENARIOS``: forms on no list) and a sensor whose error follows a
variable nobody recorded (no candidate can represent it, and it must be flagged).

The summary has one line per scenario over all seeds: how many seeds were attributed as
expected, the median error before, the range of the error after, of after/told and of
``left``. A seed × scenario table of the verdicts follows (``yes``: as expected; otherwise
what was found, ``C`` for a reported confound), and for every reported confound the paired
p-values that decided it. ``--each`` prints every seed's line as it runs.

Run: python tests/benchmarks/bench_effects.py [SEED ...] [--only TEXT] [--dwell S] [--each] [--quick]
(default seeds 0 1 2 3 4; ``--only`` keeps scenarios whose name contains TEXT; repeat it for several.)
"""

from __future__ import annotations

import argparse
import statistics
import time

from canical.calibration.evaluation import EffectScore, score_scenario
from canical.sim.scenarios import SCENARIOS, SMOOTH_SCENARIOS, UNEXPLAINED

SEEDS = [0, 1, 2, 3, 4]


def verdict(r: EffectScore) -> str:
    """One short cell: yes, or what the loop did instead."""
    if r.correct:
        return "yes"
    found = "+".join(r.found) or "-"
    return f"NO {found}{' C' if r.confounded else ''}"


def seed_line(name: str, r: EffectScore) -> str:
    """One scenario on one seed, as it ran."""
    found = ", ".join(r.found) or "-"
    if r.confounded:
        found += "; confounded: " + " | ".join(" / ".join(g) for g in r.confounded)
    left = f"{r.unexplained_ratio:5.1f}{'!' if r.unexplained else ' '}"
    return (f"{name[:58]:58s} {r.rms_before:7.4f} {r.rms_after:7.4f} {r.rms_oracle:7.4f} "
            f"{r.rms_after / r.rms_oracle:6.2f} {left}  {'yes' if r.correct else 'NO '} {found}")


def span(values: list[float], fmt: str) -> str:
    """min–max of a quantity over the seeds (one value: itself)."""
    lo, hi = min(values), max(values)
    return format(lo, fmt) if lo == hi else f"{lo:{fmt}}-{hi:{fmt}}"


def summary_line(name: str, runs: list[EffectScore]) -> str:
    """One scenario over every seed: attributed as expected, and the spread of its errors."""
    ok = sum(r.correct for r in runs)
    flagged = sum(r.unexplained for r in runs)
    return (f"{name[:58]:58s} {ok:>2d}/{len(runs):<2d} {statistics.median(r.rms_before for r in runs):7.4f} "
            f"{span([r.rms_after for r in runs], '.4f'):>15s} "
            f"{span([r.rms_after / r.rms_oracle for r in runs], '.2f'):>11s} "
            f"{span([r.unexplained_ratio for r in runs], '.1f'):>10s} {flagged:>3d}")


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("seeds", nargs="*", type=int, default=SEEDS)
    parser.add_argument("--only", action="append", default=[])
    parser.add_argument("--dwell", type=float, default=10.0)
    parser.add_argument("--each", action="store_true", help="print every seed's line as it runs")
    parser.add_argument("--quick", action="store_true", help="small sizes: checks the script runs")
    args = parser.parse_args()
    scenarios = [sc for sc in (*SCENARIOS, *SMOOTH_SCENARIOS, UNEXPLAINED)
                 if not args.only or any(o in sc.name for o in args.only)]
    if args.quick:
        args.seeds, scenarios = args.seeds[:1], scenarios[:1]
    runs: dict[str, list[EffectScore]] = {sc.name: [] for sc in scenarios}
    decisions: list[str] = []
    t0 = time.perf_counter()
    for seed in args.seeds:
        if args.each:
            print(f"seed {seed}, dwell {args.dwell:g} s\n{'scenario':58s} {'before':>7s} {'after':>7s} "
                  f"{'told':>7s} {'a/told':>6s} {'left':>6s}  ok  found")
        for sc in scenarios:
            r = score_scenario(sc, seed, args.dwell)
            runs[sc.name].append(r)
            decisions += [f"  seed {seed} {sc.name[:40]}: "
                          + ", ".join(f"{n} p={p:.2g}" for n, p in g.items())
                          for g in r.paired_p]
            if args.each:
                print(seed_line(sc.name, r), flush=True)
    seconds = time.perf_counter() - t0
    n_ok = sum(r.correct for rs in runs.values() for r in rs)
    print(f"{len(scenarios)} scenarios x {len(args.seeds)} seeds ({', '.join(map(str, args.seeds))}), "
          f"dwell {args.dwell:g} s: {n_ok}/{len(scenarios) * len(args.seeds)} attributed as expected, "
          f"{seconds:.0f} s\n")
    print(f"{'scenario':58s} {'ok':>5s} {'before':>7s} {'after (range)':>15s} {'a/told':>11s} "
          f"{'left':>10s} {'!':>3s}")
    for name, rs in runs.items():
        print(summary_line(name, rs))
    if len(args.seeds) > 1:
        print(f"\n{'verdicts':58s} " + " ".join(f"{'seed ' + str(s):>9s}" for s in args.seeds))
        for name, rs in runs.items():
            print(f"{name[:58]:58s} " + " ".join(f"{verdict(r):>9s}" for r in rs))
    if decisions:
        print("\nreported confounds: one-sided paired p that the first named predicts held-out plateaus "
              "better than each other one (confounded when every p >= the level, 0.01)")
        print("\n".join(decisions))


if __name__ == "__main__":
    main()
