"""Benchmark: the closed loop on blind cases (effects, channel trajectories and drifts drawn at random).

Each case is drawn by :func:`canical.sim.blind.draw_case` from a seed: an effect form (none, a
channel's level, rate of change or lag, a warm-up, or a form no candidate lists), a trajectory of the
channel (cycling, ramps, steps, a level per plateau, noise only) and a drift of the sensor (none,
random walk, flicker, bias steps). Scored per case:

* right attribution: an effect of the channel is blamed on it (any of its forms, in the set), a
  warm-up is taken by a time candidate (in the set: a form of time adopted among confounded twins
  counts, as a channel's form adopted so counts as blamed), and where no channel may be blamed none
  is;
* false blame: a channel term in the set where the case has no visible channel effect (a clean or
  drifting sensor, or a trajectory of noise only);
* confounds: groups reported, and whether the set was corrected (one adopted) or the channel's
  form lost to the session's drift;
* held-out error against a model told the true form (where a term writes it);
* separable: whether that told form itself predicts held-out plateaus better than the drift of the
  session the loop sets against it. Where it does not, the session cannot tell the effect from the
  sensor's drift, and the listed class's attribution is scored apart as well.

Development seeds are any seed but the blind ones (``--seeds``, printed case by case, drawn from
any class or, with ``--class``, from one, whose criterion is then printed too; the loop was shaped
on 0-99 of any class and 1000-1159, 1400-1479 and a few others of the two narrower ones). The blind
seeds are drawn from BLIND_ROOT, picked once at random and never printed case by case: only the
scores (``--blind N``), N cases of each class: any case; a drifting sensor with no channel effect
(how often a drift is blamed on a channel); a real effect of a form the loop lists (how often it is
attributed). ``--root`` draws them from another root: a fresh blind sample, scored once.

Run: python tests/benchmarks/bench_blind.py [--seeds 0 1 ...] [--class drift|listed] [--blind N]
[--root R] [--quick]
Prints figures; asserts nothing.
"""

from __future__ import annotations

import argparse
import time

import numpy as np

from canical.calibration.evaluation import score_scenario
from canical.sim.blind import ANY, DRIFT_ONLY, LISTED_EFFECT, BlindCase, BlindClass, draw_case

#: Picked once at random (secrets.randbits(48)); the seeds it draws are never looked at one by one.
BLIND_ROOT = 27569707891287


#: ``--class``: the classes a criterion is judged on, by the name the command line gives them.
CLASSES = {"any": ANY, "drift": DRIFT_ONLY, "listed": LISTED_EFFECT}


def judge(seed: int, dwell_s: float, within: BlindClass = ANY) -> dict[str, object]:
    return judge_case(draw_case(seed, within), dwell_s)


def judge_case(case: BlindCase, dwell_s: float) -> dict[str, object]:
    r = score_scenario(case.scenario, seed=case.seed, dwell_s=dwell_s)
    blamed = "temp_c" in r.written_channels
    other = any(c != "temp_c" for c in r.written_channels)  # a distractor blamed
    if case.time_effect:
        right = any(n.startswith("time:") for n in r.adopted) and not blamed and not other
    elif case.blame:
        right = blamed and not other
    else:
        right = not blamed and not other
    told = bool(case.scenario.oracle_terms) and (case.blame is not None or case.time_effect)
    return {"case": case.describe, "right": right, "false_blame": case.blame is None and (blamed or other),
            "no_effect": case.blame is None and not case.time_effect, "confounds": len(r.confounded),
            "ratio": r.rms_after / r.rms_oracle if told else float("nan"), "found": r.found,
            "twins": tuple(n for n in r.adopted if n not in r.found),
            "written": r.written_channels, "unexplained": r.unexplained_ratio,
            "separable": r.drift_separable if case.blame and case.scenario.oracle_terms else None}


def summary(rows: list[dict[str, object]]) -> str:
    n = len(rows)
    right = sum(bool(r["right"]) for r in rows)
    clean = [r for r in rows if r["no_effect"]]
    false = sum(bool(r["false_blame"]) for r in clean)
    ratios = np.array([r["ratio"] for r in rows], dtype=float)
    ratios = ratios[np.isfinite(ratios)]
    within = int(np.sum(ratios <= 2.0))
    median = float(np.median(ratios)) if ratios.size else float("nan")
    return (f"right {right}/{n}; false blame {false}/{len(clean)} cases with no visible channel effect; "
            f"confounds reported in {sum(int(r['confounds']) > 0 for r in rows)}/{n}; held-out within 2x "
            f"of told {within}/{ratios.size} (median ratio {median:.2f})")


def criterion(within: BlindClass, rows: list[dict[str, object]]) -> str:
    """The issue's bar for the class: false blame of a drift, or listed effects attributed."""
    n = len(rows)
    if within is DRIFT_ONLY:
        blamed = sum(bool(r["false_blame"]) for r in rows)
        return f"\n  blamed on a channel: {blamed}/{n} (bar: at most 1 in 20)"
    if within is LISTED_EFFECT:
        ratios = np.array([r["ratio"] for r in rows], dtype=float)
        apart = [r for r in rows if r["separable"]]
        return (f"\n  attributed: {sum(bool(r['right']) for r in rows)}/{n} (bar: every one); held-out "
                f"within 2x of told {int(np.sum(ratios <= 2.0))}/{n}"
                f"\n  where the told form predicts better than the drift it meets: attributed "
                f"{sum(bool(r['right']) for r in apart)}/{len(apart)}; elsewhere "
                f"{sum(bool(r['right']) for r in rows if not r['separable'])}/{n - len(apart)}")
    return ""


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--seeds", type=int, nargs="*", default=list(range(20)),
                    help="development seeds, printed case by case (any seed but the blind ones)")
    ap.add_argument("--blind", type=int, default=0, help="blind seeds to draw from --root (scores only)")
    ap.add_argument("--root", type=int, default=BLIND_ROOT,
                    help="the root blind seeds are drawn from [BLIND_ROOT]; another (secrets.randbits(48), "
                         "say) draws a fresh blind sample")
    ap.add_argument("--class", dest="within", choices=sorted(CLASSES), default="any",
                    help="the class --seeds are drawn from [any]")
    ap.add_argument("--dwell", type=float, default=8.0)
    ap.add_argument("--quick", action="store_true", help="one development seed, short dwell")
    args = ap.parse_args()
    seeds, dwell = ([0], 3.0) if args.quick else (args.seeds, args.dwell)
    t0 = time.perf_counter()
    if seeds:
        rows = []
        print(f"seeds of {CLASSES[args.within].name}, case by case:")
        for seed in seeds:
            row = judge(seed, dwell, CLASSES[args.within])
            rows.append(row)
            print(f"  {seed:3d} {row['case']:<40} right {row['right']!s:<5} found {list(row['found'])} "
                  f"{'adopted among twins ' + str(list(row['twins'])) + ' ' if row['twins'] else ''}"
                  f"set {list(row['written'])} ratio {row['ratio']:.2f} left {row['unexplained']:.1f}x"
                  f"{' (told form no better than the drift)' if row['separable'] is False else ''}",
                  flush=True)
        print("these seeds: " + summary(rows) + criterion(CLASSES[args.within], rows))
    if args.blind:
        for k, within in enumerate((ANY, DRIFT_ONLY, LISTED_EFFECT)):
            root = np.random.default_rng(args.root if k == 0 else [args.root, k])
            rows = [judge(int(s), dwell, within) for s in root.integers(100, 2**31 - 1, args.blind)]
            print(f"blind, {within.name}: " + summary(rows) + criterion(within, rows), flush=True)
    print(f"({time.perf_counter() - t0:.0f} s)")


if __name__ == "__main__":
    main()
