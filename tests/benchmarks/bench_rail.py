"""Benchmark: sensors that compress near their rail, calibrated with and without a higher order.

Prints figures; asserts nothing. Run: python tests/benchmarks/bench_rail.py [--quick] [--seeds N] [--blind N]

Development seeds are 1000 onwards (``--seeds``, printed seed by seed). Blind seeds are drawn from
BLIND_ROOT, picked once at random and never printed one by one: only their scores (``--blind``).

Each seed draws a sensor (:func:`canical.sim.compression.draw_compressing`): a rail at 60-90 %
of the table's range, an output that bends before it (hard knees and gentle bends), noise and
sensitivity at random. Per seed, the error against the truth over the fitted plateaus' span
(noise-free, 400 rates) of:

* ``orders<=3``: the size chosen among orders 1-3 only;
* ``chosen``: the size canical chooses (orders 4-5 taken only when clearly better);
* ``hindsight``: the best single polynomial, forward or inverse, of order 1-9, picked by its
  true error: a model fitted with hindsight on the unclipped plateaus;
* ``best size``: the best segmented inverse polynomial of any size (1-6 segments, order 1-7),
  picked by its true error: a stricter reference, as no choice from the data can beat it.
"""

from __future__ import annotations

import os

os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")  # before numpy loads its BLAS

import argparse
import sys
from pathlib import Path

import numpy as np

from canical.calibrate.model_fit import ModelSpec
from canical.calibrate.model_selection import select_model
from canical.calibration.pipeline import BaseFit, CalibrateOptions, fit_base
from canical.errors import CanicalError
from canical.models.kinds import SEGMENTED_INVERSE
from canical.sim.compression import CompressingCase, draw_compressing

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from support.rail_truth import error_of, hindsight

BLIND_ROOT = 7493028996101
BENDS = {"hard knee": (1.02, 1.3), "gentle bend": (1.3, 2.0)}


def best_size(case: CompressingCase, base: BaseFit) -> float:
    errors = []
    for order in range(1, 8):
        for segments in range(1, 7):
            try:
                errors.append(error_of(case, base, ModelSpec(SEGMENTED_INVERSE, segments, order, 0)))
            except (CanicalError, np.linalg.LinAlgError):
                continue
    return min(errors)


def one_seed(seed: int, bend: tuple[float, float]) -> tuple[float, float, float, float, str]:
    case = draw_compressing(seed, asymptote=bend)
    base = fit_base(case.session, CalibrateOptions(extend=False))
    start = ModelSpec(SEGMENTED_INVERSE, 4, 2, 0)
    low, _ = select_model(base.points, start, high_orders=())
    chosen = base.fitted.spec
    size = f"{chosen.n_segments}x{chosen.order}"
    return (error_of(case, base, low), error_of(case, base, chosen), hindsight(case, base),
            best_size(case, base), size)


def scores(rows: list[tuple[float, float, float, float, str]]) -> str:
    """The aggregate figures of a list of seeds' rows."""
    low, chosen, hind, best = (np.array([r[k] for r in rows]) for k in range(4))
    n = len(rows)
    return (f"median: orders<=3 {np.median(low):.5f}, chosen {np.median(chosen):.5f} "
            f"({np.median(low) / np.median(chosen):.1f}x lower); worse than orders<=3 in "
            f"{int(np.sum(chosen > 1.05 * low))}/{n}\n"
            f"  within 1.2x of the hindsight polynomial in {int(np.sum(chosen <= 1.2 * hind))}/{n}; "
            f"of the best size: orders<=3 in {int(np.sum(low <= 1.2 * best))}/{n}, chosen in "
            f"{int(np.sum(chosen <= 1.2 * best))}/{n} (median chosen/best {np.median(chosen / best):.2f})")


def development(n: int) -> None:
    print(f"sensors compressing near their rail, {n} seeds per bend (seeds 1000..{1000 + n - 1}); "
          "error against the truth, deg/s rms")
    for name, bend in BENDS.items():
        rows = [one_seed(1000 + i, bend) for i in range(n)]
        print(f"\n{name} (asymptote {bend[0]:g}-{bend[1]:g}x the rail)")
        print("  seed   orders<=3    chosen  size  hindsight  best size  chosen/hindsight  chosen/best")
        for i, (lo, ch, hi, bs, size) in enumerate(rows):
            print(f"  {1000 + i:4d}  {lo:10.5f} {ch:9.5f}  {size:>4}  {hi:9.5f}  {bs:9.5f}  {ch / hi:16.2f}"
                  f"  {ch / bs:11.2f}")
        print("  " + scores(rows))


def blind(n: int, stream: int = 0) -> None:
    """Scores on ``n`` seeds per bend drawn from BLIND_ROOT (``stream`` 0: the blind seeds; quick
    mode draws from another stream, so a CI log never shows a blind seed's figures)."""
    for k, (name, bend) in enumerate(BENDS.items()):
        seeds = np.random.default_rng([BLIND_ROOT, stream, k]).integers(10_000, 2**31 - 1, n)
        rows = [one_seed(int(s), bend) for s in seeds]
        print(f"\nblind, {name}, {n} seeds: " + scores(rows))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="two seeds per bend: checks the script runs")
    parser.add_argument("--seeds", type=int, default=12, help="development seeds per bend [12]")
    parser.add_argument("--blind", type=int, default=0, help="blind seeds per bend (scores only) [0]")
    args = parser.parse_args()
    development(2 if args.quick else args.seeds)
    if args.quick:
        blind(1, stream=1)
    elif args.blind:
        blind(args.blind)


if __name__ == "__main__":
    main()
