"""Accuracy on the paper's protocol: every model variant on held-out rates, over several seeds.

Training: -60..60 deg/s in 3 deg/s steps; judged on a second session at the rates
midway between (-58.5..58.5). Prints held-out rms/max and the largest jump of
the corrected rate at a segment point. Run: python tests/benchmarks/bench_accuracy.py [--quick]
"""

from __future__ import annotations

import argparse

import numpy as np

from canical.calibration.evaluation import compare_models
from canical.calibration.pipeline import CalibrateOptions
from canical.sim.sessions import between_rates_session, paper_session

VARIANTS = (
    ("common: segmented-linear 0, ±10", CalibrateOptions(model="segmented-linear")),
    ("forward-poly, order by CV", CalibrateOptions(model="forward-poly")),
    ("paper: 4 seg, order 2, free joins", CalibrateOptions(segments=4, order=2, smoothness=None)),
    ("4 seg, order 2, C0 joins", CalibrateOptions(segments=4, order=2, smoothness=0)),
    ("4 seg, order 2, C1 joins", CalibrateOptions(segments=4, order=2, smoothness=1)),
    ("auto size, free joins", CalibrateOptions(smoothness=None)),
    ("auto size, C0 joins (default)", CalibrateOptions(smoothness=0)),
    ("auto size, C1 joins", CalibrateOptions(smoothness=1)),
)
SEEDS = range(8)


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes: checks the script runs")
    args = parser.parse_args()
    seeds = range(1) if args.quick else SEEDS
    variants = VARIANTS[:2] if args.quick else VARIANTS
    rows: dict[str, list[tuple[float, float, float, str]]] = {label: [] for label, _ in variants}
    for seed in seeds:
        scores = compare_models(paper_session(seed=seed), between_rates_session(seed=100 + seed), variants)
        for s in scores:
            jumps = getattr(s.model, "jumps", None)
            jump = float(np.max(np.abs(jumps()), initial=0.0)) if jumps else 0.0
            rows[s.label].append((s.test_rms_dps, s.test_max_dps, jump, s.spec))
    common = np.mean([r[0] for r in rows[VARIANTS[0][0]]])
    print(f"held-out error over {len(seeds)} simulated sensors' sessions (mean over seeds), deg/s")
    print(f"{'variant':36s} {'rms':>8s} {'max':>8s} {'vs common':>10s} {'max jump':>10s}  sizes chosen")
    for label, _ in variants:
        r = np.array([x[:3] for x in rows[label]])
        sizes = sorted({x[3].split(" ", 1)[1] for x in rows[label]})
        print(f"{label:36s} {r[:, 0].mean():8.4f} {r[:, 1].mean():8.4f} {common / r[:, 0].mean():9.1f}x "
              f"{r[:, 2].max():10.2e}  {'; '.join(sizes)[:60]}")


if __name__ == "__main__":
    main()
