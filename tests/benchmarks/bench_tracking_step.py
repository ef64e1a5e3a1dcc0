"""Cost of the bias tracker's per-sample step (what the daemon adds per frame), in process.

Streams of 200,000 samples at 100 Hz: a standstill (windows close, the bias is learned and
slews), with the temperature reading held (as a 0.1 °C signal mostly is) or new at every
sample, with and without a cue. ``BiasTracker.step`` (the reference, on 1 and 3 axes) beside
the closure the daemon and the replay run per axis (``canical.tracking.fast_step``, bit for bit
the same). Prints µs per call, the best of ``--repeat`` runs.

Run: python tests/benchmarks/bench_tracking_step.py [--samples N] [--repeat R]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from canical.tracking.config import TrackerConfig
from canical.tracking.fast_step import fast_step
from canical.tracking.tracker import BiasTracker


def per_call_us(axes: int, samples: int, *, moving_temp: bool, cue: bool, fast: bool = False) -> float:
    rng = np.random.default_rng(0)
    rows = (0.1 + 0.05 * rng.standard_normal((samples, axes))).tolist()
    times = (np.arange(samples) / 100.0).tolist()
    temps = (25.0 + 0.01 * np.arange(samples) / 100.0 if moving_temp else np.full(samples, 25.0)).tolist()
    cues = [0.0] * samples if cue else [None] * samples
    tracker = BiasTracker(("x", "y", "z")[:axes], TrackerConfig(arw_deg_rt_h=0.3,
                                                                cue_threshold=0.1 if cue else None))
    if fast:
        one = fast_step(tracker).step
        values = [r[0] for r in rows]
        start = time.perf_counter()
        for t, v, temp, c in zip(times, values, temps, cues, strict=True):
            one(t, v, temp, c)
        return (time.perf_counter() - start) / samples * 1e6
    step = tracker.step
    start = time.perf_counter()
    for t, r, temp, c in zip(times, rows, temps, cues, strict=True):
        step(t, r, temp, c)
    return (time.perf_counter() - start) / samples * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--samples", type=int, default=200_000)
    parser.add_argument("--repeat", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="small sizes: checks the script runs")
    args = parser.parse_args()
    if args.quick:
        args.samples, args.repeat = 2_000, 1
    print("| step | axes | temperature | cue | µs per call (best of runs) |\n|---|---|---|---|---|")
    for name, axes, fast in (("BiasTracker.step", 1, False), ("BiasTracker.step", 3, False),
                             ("fast_step (daemon, replay)", 1, True)):
        for moving_temp in (False, True):
            for cue in (False, True):
                best = min(per_call_us(axes, args.samples, moving_temp=moving_temp, cue=cue, fast=fast)
                           for _ in range(args.repeat))
                temp = "new every sample" if moving_temp else "held"
                print(f"| {name} | {axes} | {temp} | {'yes' if cue else 'no'} | {best:.2f} |")


if __name__ == "__main__":
    main()
