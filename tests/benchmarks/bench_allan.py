"""How well the IEEE 952 read-outs recover known noise terms, over many seeds of synthetic noise.

Per case: relative error of each estimate (median and 90th percentile of |error|, worst),
how often the term was resolved, how often its stated interval held the true value, and how
often a term the noise does not have was claimed.
Run: python tests/benchmarks/bench_allan.py [seeds] [--quick]
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from support.allan_noise import flicker_rate, rate_random_walk, rrw_for_crossover, white_rate

from canical.calibrate.allan import allan_deviation, noise_terms


def case_white(rng):
    arw = rng.uniform(0.05, 2.0)
    return 100.0, white_rate(rng, 60_000, 100.0, arw), {"arw": arw}


def case_white_rrw(rng):
    fs, n = 10.0, 200_000
    arw, crossover = rng.uniform(0.1, 1.0), rng.uniform(10.0, 60.0)
    rrw = rrw_for_crossover(arw, crossover)
    return fs, white_rate(rng, n, fs, arw) + rate_random_walk(rng, n, fs, rrw), {"arw": arw, "rrw": rrw}


def case_white_flicker(rng):
    fs, n = 10.0, 200_000
    bi = rng.uniform(2.0, 20.0)
    x = white_rate(rng, n, fs, 0.2) + flicker_rate(rng, n, fs, bi)
    return fs, x, {"arw": 0.2, "bias_instability": bi}


def case_plateaus(rng):
    """Four 30 s zero-rate plateaus at 200 Hz, as in a turntable session."""
    fs = 200.0
    records = [white_rate(rng, 6000, fs, 0.4) + rate_random_walk(rng, 6000, fs, 5.0) for _ in range(4)]
    return fs, records, {"arw": 0.4, "rrw": 5.0}


CASES = {
    "white, 10 min at 100 Hz": case_white,
    "white + RRW, 5.6 h at 10 Hz": case_white_rrw,
    "white + flicker, 5.6 h at 10 Hz": case_white_flicker,
    "4 zero-rate plateaus of 30 s": case_plateaus,
}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("seeds", nargs="?", type=int, default=40)
    parser.add_argument("--quick", action="store_true", help="small sizes: checks the script runs")
    args = parser.parse_args()
    seeds = 1 if args.quick else args.seeds
    t0 = time.perf_counter()
    print(f"{'case':32s} {'term':17s} {'resolved':>8s} {'|err| med':>9s} {'p90':>6s} {'max':>6s} "
          f"{'in interval':>11s}")
    for name, make in CASES.items():
        rows: dict[str, list[tuple[bool, float, bool]]] = {}
        claimed = 0  # terms resolved that the noise does not have
        for seed in range(seeds):
            fs, data, truth = make(np.random.default_rng(seed))
            terms = noise_terms(allan_deviation(data if isinstance(data, list) else [data], fs))
            claimed += sum(t.resolved for key, t in terms.items() if key not in truth)
            for key, value in truth.items():
                t = terms[key]
                rows.setdefault(key, []).append((t.resolved, t.value / value - 1.0, t.low <= value <= t.high))
        for key, r in rows.items():
            res = [x for x in r if x[0]]
            err = np.abs([x[1] for x in res]) if res else np.array([np.nan])
            cover = sum(x[2] for x in res)
            print(f"{name:32s} {key:17s} {len(res):4d}/{len(r):<3d} {np.median(err):9.1%} "
                  f"{np.percentile(err, 90):6.1%} {np.max(err):6.1%} {cover:7d}/{len(res):<3d}")
        print(f"{name:32s} {'terms not present':17s} claimed {claimed} times")
    print(f"\n{seeds} seeds per case, {time.perf_counter() - t0:.0f} s")


if __name__ == "__main__":
    main()
