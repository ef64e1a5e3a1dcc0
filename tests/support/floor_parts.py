"""What the floor of the carried zero-rate error is made of, standstill by standstill, against the
simulated truth: the standstill's own noise, the tracker's error from the stop before, the rest.

Run: python tests/support/floor_parts.py DIR...   (fleets ``sets_fleets.py --keep`` built)

Why: after a proposed set every fleet's carried error sits near 0.002 deg/s. Per standstill its
squared mean is E[m²] = b² + var(m): b the bias the set and the tracker leave (the true bias less
the one applied as the stop began), var(m) the noise of the mean of its rows. This splits the
after figure into those, splits b into the tracker's error at the end of the stop before and what
the set and the tracker's prediction leave between the stops, and compares three estimates of
var(m) from the data alone with the truth's: the naive sample variance over n, the variance of
one-second means over their count, and the same about a line (a stop's slow trend left out); and
per sensor, how far ``fleet replay``'s figure less the noise lies from the truth, in its own 1σ.
"""

from __future__ import annotations

import csv
import itertools
import math
import sys
from dataclasses import dataclass
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from support.carried_truth import _runs, replayed, wrong_slope

SECOND = 100  # rows in a second of a simulated drive


@dataclass(frozen=True)
class Part:
    """One judged standstill after the new set: its figure and its parts (deg/s, variances in
    (deg/s)²)."""

    m: float  # the carried figure: mean output less the bias applied as it began
    b: float  # the truth's: mean true bias less the applied one
    noise: float  # the mean of its noise (white and vibration), the truth's
    prev_noise: float  # the stop before's noise of the mean (guard seconds left out): learned by the tracker
    naive_var: float  # sample variance / n
    second_var: float  # variance of one-second means / their count (scaled to n rows)
    line_var: float  # the same, the one-second means taken about a line


def _mean_var(x: np.ndarray, detrend: bool) -> float:
    """The variance of x's mean from its one-second means (about a line if ``detrend``)."""
    k = len(x) // SECOND
    means = x[: k * SECOND].reshape(k, SECOND).mean(axis=1)
    if detrend:
        t = np.arange(k)
        resid = means - np.polyval(np.polyfit(t, means, 1), t)
        return float(resid @ resid / (k - 2) * SECOND / len(x))
    return float(np.var(means, ddof=1) * SECOND / len(x))


def _inner_noise(noise: np.ndarray, run: tuple[int, int]) -> float:
    """The mean noise over a run less its first and last second (the tracker's guard windows)."""
    a, b = run
    inner = noise[a + SECOND: b - SECOND]
    return float(inner.mean()) if len(inner) else 0.0


def _all_runs(cols: dict[str, np.ndarray]) -> list[tuple[int, int]]:
    """Every run of stopped rows, power-on by power-on (the first and short ones too)."""
    t, stop = cols["time_s"], cols["speed_mps"] < 0.1
    new = np.concatenate([[True], t[1:] < t[:-1]])
    edges = [*np.flatnonzero(new | np.concatenate([[True], stop[1:] != stop[:-1]])).tolist(), len(t)]
    return [(a, b) for a, b in itertools.pairwise(edges) if stop[a]]


def parts(folder: Path, seed: int, index: int) -> list[Part]:
    out = []
    for drive in replayed(folder, seed, index):
        cols, (rb, _), (ra, ba) = drive.cols, drive.before, drive.after
        target = drive.true_bias + ra - rb  # the true bias after the new set
        out_rate = ra - cols["true_rate_dps"]
        every = _all_runs(cols)
        for a, b in _runs(cols):
            prev = max((r for r in every if r[1] <= a), key=lambda r: r[1])
            x = out_rate[a:b]
            out.append(Part(float(x.mean()) - ba[a], float(target[a:b].mean()) - ba[a],
                            float((out_rate[a:b] - target[a:b]).mean()),
                            _inner_noise(out_rate - target, prev),
                            float(np.var(x, ddof=1) / len(x)), _mean_var(x, False), _mean_var(x, True)))
    return out


def _ms(values: list[float]) -> float:
    return sum(v * v for v in values) / len(values)


@dataclass(frozen=True)
class Reported:
    """What ``fleet replay`` reported after the new set, from replay.csv: the sum over the
    standstills of m² less their estimated noise, and its 1σ."""

    less_noise_sq: float
    sd: float

    def z(self, b_sq: float) -> float:
        """How many of its 1σ the reported sum lies from the truth's sum of b²."""
        return (self.less_noise_sq - b_sq) / self.sd


def reported(folder: Path, sensor: str) -> Reported:
    r = next(r for r in csv.DictReader((folder / "replay.csv").open()) if r["sensor_id"] == sensor)
    n = int(r["standstills"])
    less_sq = n * (float(r["carried_after_dps"]) ** 2 - float(r["carried_noise_after_dps"]) ** 2)
    bound = float(r["carried_less_noise_after_dps"]) + float(r["carried_less_noise_after_sd_dps"])
    return Reported(less_sq, n * bound**2 - less_sq)  # the +1σ bound is √((sum + 1σ) / n)


def row(name: str, got: list[Part], said: Reported | None) -> str:
    m2, b2, n2 = _ms([p.m for p in got]), _ms([p.b for p in got]), _ms([p.noise for p in got])
    prev2, rest2 = _ms([p.prev_noise for p in got]), _ms([p.b + p.prev_noise for p in got])
    naive, second, line = (sum(v) / len(got) for v in zip(*((p.naive_var, p.second_var, p.line_var)
                                                             for p in got), strict=True))
    less = max(m2 - line, 0.0)
    z = f"{said.z(b2 * len(got)):+.2f}" if said else "-"
    return (f"| {name} | {len(got)} | {math.sqrt(m2):.5f} | {math.sqrt(b2):.5f} | {math.sqrt(n2):.5f} | "
            f"{math.sqrt(naive):.5f} | {math.sqrt(second):.5f} | {math.sqrt(line):.5f} | "
            f"{math.sqrt(less):.5f} | {math.sqrt(prev2):.5f} | {math.sqrt(rest2):.5f} | {z} |")


def main(folders: list[Path]) -> None:
    print("After the new set, RMS over the standstills (deg/s): the carried figure m; the truth's b (true "
          "bias less the applied one) and the noise of the mean; var(m) estimated naive, from one-second "
          "means, the same about a line; m less that; b split: the noise of the stop before's mean, "
          "which the tracker learned as bias, and b less it (what the set and the tracker's prediction leave "
          "between the stops); z: fleet replay's sum of m² less the noise, less the truth's sum of b², "
          "over its reported 1σ.\n")
    print("| fleet: sensor | stops | m | b | noise | naive | 1 s means | about a line | m less noise | "
          "noise learned at the stop before | b less it | replay's figure: z |")
    print("|---|---|---|---|---|---|---|---|---|---|---|---|")
    pooled: list[Part] = []
    zs = []
    for folder, seed, index, sensor in wrong_slope(folders):
        got = parts(folder, seed, index)
        pooled += got
        said = reported(folder, sensor)
        zs.append(said.z(sum(p.b**2 for p in got)))
        print(row(f"{folder.name}: {sensor}", got, said), flush=True)
    print(row("**pooled**", pooled, None))
    print(f"\nz over {len(zs)} sensors: mean {sum(zs) / len(zs):+.2f}, RMS "
          f"{math.sqrt(sum(z * z for z in zs) / len(zs)):.2f}, beyond 2: {sum(abs(z) > 2 for z in zs)}")

if __name__ == "__main__":
    main([Path(a) for a in sys.argv[1:]])
