"""Three axes: multi-axis validation error with the coupling against per-axis calibration alone.

A simulated triad per seed (coupling 0.4–2 %, per-axis nonlinearity, ±150 deg/s): three
single-axis sessions (x, -y, z) calibrate it (``canical.calibration.imu_pipeline``); a multi-axis session
(12 plateaus of 3 s or the dwell, all three axes turning at once, up to ±120 deg/s), never
fitted, judges it. Prints
per seed the validation plateau error (rms and max over the three axes) of today's per-axis
calibration and of the IMU set, their ratio, the joint refits kept, and the coupling's recovery
(largest error of a term and largest error in standard errors).
Run: python tests/benchmarks/bench_triad.py [--quick] [--dwell S] [--seeds N]
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from canical.calibration.imu_pipeline import calibrate_imu
from canical.calibration.pipeline import CalibrateOptions
from canical.sim.triad import axis_session, multi_axis_rates, multi_axis_session, random_triad


def run_seed(seed: int, dwell_s: float) -> dict[str, float]:
    triad = random_triad(seed)
    sessions = [axis_session(triad, a, dwell_s=dwell_s, seed=100 * seed + k)
                for k, a in enumerate(("x", "-y", "z"))]
    # The validation plateaus long enough on every axis whatever the dwell of the calibration's.
    multi = multi_axis_session(triad, multi_axis_rates(12, seed=seed), dwell_s=max(dwell_s, 3.0),
                               seed=100 * seed + 9)
    start = time.perf_counter()
    result = calibrate_imu([*sessions, multi], CalibrateOptions(), sensor_id="SIM")
    seconds = time.perf_counter() - start
    check = result.errors[-1]
    truth = np.linalg.inv(triad.coupling) @ np.diag(np.diag(triad.coupling))  # per-axis models fix the scale
    err = result.coupling.matrix - truth
    return {
        "before": float(np.sqrt(np.mean(np.square(check.before_rms_dps)))),
        "after": float(np.sqrt(np.mean(np.square(check.after_rms_dps)))),
        "after_max": check.after_max_dps,
        "refits": result.joint_refits,
        "term_err": float(np.abs(err).max()),
        "z": float(np.abs(err / result.coupling.standard_errors).max()),
        "plateaus": check.plateaus,
        "seconds": seconds,
    }


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes: checks the script runs")
    parser.add_argument("--dwell", type=float, default=2.0, help="plateau dwell, s [2]")
    parser.add_argument("--seeds", type=int, default=5, help="number of seeds [5]")
    args = parser.parse_args()
    seeds = range(1) if args.quick else range(args.seeds)
    dwell = 1.5 if args.quick else args.dwell
    print(f"multi-axis validation plateaus, dwell {dwell:g} s; error rms over x, y, z (deg/s)")
    print("| seed | per-axis only | with coupling | max | ratio | refits | worst term | worst /SE | s |")
    print("|---|---|---|---|---|---|---|---|---|")
    rows = []
    for seed in seeds:
        r = run_seed(seed, dwell)
        rows.append(r)
        print(f"| {seed} | {r['before']:.4f} | {r['after']:.4f} | {r['after_max']:.4f} | "
              f"{r['before'] / r['after']:.0f}x | {r['refits']:g} | {r['term_err']:.1e} | {r['z']:.1f} | "
              f"{r['seconds']:.1f} |")
    after = np.array([r["after"] for r in rows])
    ratio = np.array([r["before"] / r["after"] for r in rows])
    print(f"with coupling: rms {np.sqrt(np.mean(after**2)):.4f} deg/s over seeds, worst seed "
          f"{after.max():.4f}; improvement {ratio.min():.0f}x at least")


if __name__ == "__main__":
    main()
