"""Benchmark: run-time cost of the calibration models, and calibrate time for 1M samples.

Prints figures; asserts nothing. Run: python tests/benchmarks/bench_models.py [--quick]

BLAS runs on one thread (``OPENBLAS_NUM_THREADS=1`` unless set): the closed loop's many small
least squares gain nothing from threads, and on a shared machine threads make them several
times slower and the figure meaningless.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy loads its BLAS

import argparse
import contextlib
import io
import tempfile
import time
from pathlib import Path

import numpy as np

from canical.calibration.pipeline import CalibrateOptions, calibrate, fit_base
from canical.commands.cli import main as cli_main
from canical.sessions.csv_file import format_session
from canical.sim.gyro import GyroModel
from canical.sim.sessions import paper_rates, paper_session, sweep_session


def best_of(fn, repeat: int = 5) -> float:
    times = []
    for _ in range(repeat):
        t0 = time.perf_counter()
        fn()
        times.append(time.perf_counter() - t0)
    return min(times)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes: checks the script runs")
    quick = parser.parse_args().quick
    repeat = 1 if quick else 5
    session = paper_session()
    models = {
        "segmented-inverse (auto, C0)": fit_base(session, CalibrateOptions()),
        "segmented-inverse (4 seg, order 2)": fit_base(session, CalibrateOptions(segments=4, order=2)),
        "segmented-linear": fit_base(session, CalibrateOptions(model="segmented-linear")),
        "forward-poly (order 3, Newton)": fit_base(session, CalibrateOptions(model="forward-poly", order=3)),
        "forward-poly (order 6, Newton)": fit_base(session, CalibrateOptions(model="forward-poly", order=6)),
    }
    n = 10_000 if quick else 1_000_000
    rng = np.random.default_rng(0)
    base = models["segmented-inverse (auto, C0)"]
    lo, hi = base.fitted.model.span
    dv = rng.uniform(lo, hi, n)

    print(f"vectorised evaluation of {n:,} samples (best of {repeat}):")
    rates = {}
    for name, fit in models.items():
        seconds = best_of(lambda fit=fit: fit.fitted.model.evaluate(dv), repeat)
        rates[name] = n / seconds
        print(f"  {name:38s} {n / seconds / 1e6:8.2f} M samples/s")
    ref = rates["forward-poly (order 3, Newton)"]
    print(f"  segmented-inverse / forward-poly(3) throughput ratio: "
          f"{rates['segmented-inverse (auto, C0)'] / ref:.1f}x")

    print("\nscalar evaluation, one sample at a time (the daemon's per-frame path):")
    k = 1_000 if quick else 100_000
    sample = dv[:k].tolist()
    for name, fit in models.items():
        one = fit.fitted.model.evaluate_one
        seconds = best_of(lambda one=one: [one(x) for x in sample], repeat=min(repeat, 3))
        print(f"  {name:38s} {seconds / k * 1e6:8.3f} us/sample")

    samples = 150_000 if quick else 1_000_000
    print(f"\ncalibrate on a {samples:,}-sample session (auto model size, 41 rates, 3 sweeps):")
    rates_dps = np.concatenate([paper_rates(), paper_rates()[::-1], paper_rates()])
    big = sweep_session(GyroModel(), rates_dps, dwell_s=samples / 200 / len(rates_dps))
    for extend in (False, True):
        t0 = time.perf_counter()
        result = calibrate(big, CalibrateOptions(extend=extend), sensor_id="BENCH", axis="z")
        seconds = time.perf_counter() - t0
        what = "with the closed loop" if extend else "rate model only    "
        print(f"  in memory, {what}: {len(big):,} samples: {seconds:.2f} s  ({result.report.spec}, "
              f"held-out rms {result.report.held_out.rms_dps:.4f} deg/s)")
    with tempfile.TemporaryDirectory() as tmp:
        path = Path(tmp) / "big.csv"
        path.write_text(format_session(big))
        for argv in (["calibrate", str(path), "-o", f"{tmp}/c.yaml"],
                     ["apply", f"{tmp}/c.yaml", str(path), "-o", f"{tmp}/out.csv"]):
            t0 = time.perf_counter()
            with contextlib.redirect_stdout(io.StringIO()):
                assert cli_main(argv) == 0
            print(f"  canical {argv[0]:9s} from CSV ({path.stat().st_size / 1e6:.0f} MB): "
                  f"{time.perf_counter() - t0:.2f} s")


if __name__ == "__main__":
    main()
