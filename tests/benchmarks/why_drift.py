"""Why a channel was or was not blamed beside the session's drift: every share of the drift's
held-out error a channel's form removes on top of it (``search.BeyondDrift``), per seed of a
blind class, and the largest over all seeds.

The evidence behind ``BeyondDrift.large``'s ratio: on the drift class (sensors with no channel
effect) the largest share must stay below half, the share that passes whatever the paired test.
Where a share passes, the share of stretches it was not fitted on it predicts beyond their own
drift (``BeyondDrift.stretches``) is printed beside it.
The last line counts the seeds whose set carries a channel (on the drift class, each a drift
blamed on a channel).

Prints figures; asserts nothing. Run:
python tests/benchmarks/why_drift.py --class drift --seeds $(seq 1000 1159)
"""

from __future__ import annotations

import argparse
from dataclasses import dataclass

from bench_blind import CLASSES

from canical.calibration.evaluation import score_scenario
from canical.closed_loop import search
from canical.sim.blind import draw_case


@dataclass(frozen=True)
class Judged:
    seed: int
    form: str
    share: float
    p: float
    stretches: float | None


def shares_of(seed: int, within: str, dwell_s: float) -> tuple[list[Judged], tuple[str, ...]]:
    """Every share on top of the drift the loop computed on one seed, and the channels written."""
    seen: list[Judged] = []
    real = search._beyond_drift

    def logged(scorer, footing, cand, drift, alpha):
        b = real(scorer, footing, cand, drift, alpha)
        seen.append(Judged(seed, cand.name, b.gain, b.p, b.stretches))
        return b

    search._beyond_drift = logged
    try:
        case = draw_case(seed, CLASSES[within])
        r = score_scenario(case.scenario, seed=case.seed, dwell_s=dwell_s)
    finally:
        search._beyond_drift = real
    return seen, r.written_channels


def stretches(j: Judged) -> str:
    """The stretches' share beyond their drift, where it was judged."""
    return "" if j.stretches is None else f", stretches {j.stretches:.2f}"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="+", required=True)
    ap.add_argument("--class", dest="within", choices=sorted(CLASSES), default="drift")
    ap.add_argument("--dwell", type=float, default=8.0)
    args = ap.parse_args()
    every: list[Judged] = []
    blamed = 0
    for seed in args.seeds:
        seen, written = shares_of(seed, args.within, args.dwell)
        every += seen
        blamed += bool(written)
        top = max(seen, key=lambda j: j.share, default=None)
        print(f"  {seed}: {len(seen)} judged; largest "
              f"{f'{top.share:.3f} ({top.form}, p {top.p:.4f}{stretches(top)})' if top else '-'}; "
              f"set {list(written)}", flush=True)
    top = max(every, key=lambda j: j.share, default=None)
    if top:
        print(f"{len(every)} judgements on {len(args.seeds)} seeds; largest share {top.share:.3f} "
              f"(seed {top.seed}, {top.form}, p {top.p:.4f}); at half or more: "
              f"{sum(j.share >= 0.5 for j in every)}")
    print(f"a channel written into the set on {blamed}/{len(args.seeds)} seeds")


if __name__ == "__main__":
    main()
