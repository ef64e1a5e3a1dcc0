"""Benchmark: the lag of one auxiliary channel on a long session with jittered time stamps.

The closed loop's lag and derivative candidates search τ by running ``lag_filter`` (one pass of the
channel per τ tried). Time stamps written to a file at 1 kHz with microsecond resolution, or read
from a bus, are not evenly spaced to the filter's tolerance, and ``lag_filter`` then stepped the
run time's ``ChannelTracker`` sample by sample: the before. The after is ``lag_filter`` as it is now
(rows of the varying-factor recursion). One τ, both on the same record in the same run; prints
seconds per pass and the largest difference between the two (rounding).

Run: python tests/benchmarks/bench_lag_filter.py [--rows N [N ...]] [--quick]
Prints figures; asserts nothing.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from canical.sets.trackers import ChannelTracker, lag_filter


def session_channel(rows: int, seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    """A chamber temperature cycling 10-40 °C at 1 kHz, time stamps jittered and rounded to 1 µs."""
    rng = np.random.default_rng(seed)
    time_s = np.round(np.cumsum(1e-3 * (1.0 + 1e-3 * rng.standard_normal(rows))), 6)
    temp = 25.0 + 15.0 * np.sin(2 * np.pi * time_s / 600.0) + 0.02 * rng.standard_normal(rows)
    return temp, time_s


def tracker_pass(values: np.ndarray, time_s: np.ndarray, tau_s: float) -> np.ndarray:
    """The path lag_filter took on uneven time stamps before: the tracker, one call per sample."""
    tracker = ChannelTracker(tau_s)
    return np.array([tracker.update(v, t) for v, t in zip(values.tolist(), time_s.tolist(), strict=True)])


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--rows", type=int, nargs="+", default=[1_000_000, 10_000_000])
    ap.add_argument("--tau", type=float, default=60.0)
    ap.add_argument("--quick", action="store_true", help="10 000 rows (figures meaningless)")
    args = ap.parse_args()
    sizes = [10_000] if args.quick else args.rows
    print(f"lag of one channel, tau {args.tau:g} s, 1 kHz, time stamps jittered 0.1 % and rounded to 1 us")
    print(f"{'rows':>12} {'tracker s':>10} {'lag_filter s':>13} {'speed-up':>9} {'max |diff|':>11}")
    lag_filter(*session_channel(10_000), args.tau / 100.0)  # numpy's first calls, outside the timing
    for rows in sizes:
        values, time_s = session_channel(rows)
        t0 = time.perf_counter()
        before = tracker_pass(values, time_s, args.tau)
        t1 = time.perf_counter()
        after = lag_filter(values, time_s, args.tau)
        t2 = time.perf_counter()
        print(f"{rows:>12} {t1 - t0:>10.2f} {t2 - t1:>13.3f} {(t1 - t0) / (t2 - t1):>8.0f}x "
              f"{float(np.max(np.abs(after - before))):>11.2e}", flush=True)


if __name__ == "__main__":
    main()
