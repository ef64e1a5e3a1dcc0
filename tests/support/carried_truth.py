"""The carried error of a replayed fleet's wrong-slope sensors taken apart against the simulated
truth, standstill by standstill: what a set can remove and what it cannot.

Run: python tests/support/carried_truth.py DIR...   (fleets ``sets_fleets.py --keep`` built)

Why: ``fleet replay``'s carried figure is a standstill's mean output less the bias the tracker
applied as it began. Against the simulator's truth that is (a) the true bias less the applied
one, the error carried in, and (b) the standstill's own noise averaged over it (white noise and
idle vibration), the same with any set. Per sensor this prints the figure's ratio, (a)'s ratio,
(b)'s RMS, and the ratio a fleet engineer can compute without the truth: the carried error less
each standstill's noise, estimated from its one-second means, in quadrature.
"""

from __future__ import annotations

import csv
import itertools
import math
import sys
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from canical.fleet.replay import CUE_BELOW, MIN_STOP_S, blocks
from canical.sets import coefficient_file
from canical.sets.coefficients import CoefficientSet
from canical.sets.corrector import Corrector
from canical.sim.fleet import simulate_vehicle
from canical.sim.fleet_drives import drive_for
from canical.tracking.config import TrackerConfig
from canical.tracking.replay import Replayer

WRONG_SLOPE = 0.01


@dataclass(frozen=True)
class Stop:
    """One judged standstill: the figure before and after, its truth and its own noise."""

    before: float
    after: float
    truth_before: float
    truth_after: float
    noise: float  # the standstill's mean of white noise and vibration
    noise_var: float  # that mean's variance, estimated from the one-second means


def _through(cset: CoefficientSet, cols: dict[str, np.ndarray]) -> tuple[np.ndarray, np.ndarray]:
    """The set's rate and the tracker's applied bias, as ``fleet replay`` runs them."""
    corrector = Corrector(cset)
    config = TrackerConfig(cue_threshold=CUE_BELOW).for_sets([cset.fit], arw_given=False)
    rate, _ = corrector.correct_next(cols["raw"], {n: cols[n] for n in corrector.required_inputs})
    bias = Replayer(config, axes=(cset.axis,)).feed(cols["time_s"], rate, cols["temp_c"], cols["speed_mps"])
    return rate, bias[:, 0]


def _runs(cols: dict[str, np.ndarray]) -> list[tuple[int, int]]:
    """The standstills ``fleet replay`` judges (each power-on's first and short ones left out)."""
    t, stop = cols["time_s"], cols["speed_mps"] < CUE_BELOW
    new = np.concatenate([[True], t[1:] < t[:-1]])
    edges = [*np.flatnonzero(new | np.concatenate([[True], stop[1:] != stop[:-1]])).tolist(), len(t)]
    out, first = [], True
    for a, b in itertools.pairwise(edges):
        first = first or bool(new[a])
        if stop[a]:
            if not first and t[b - 1] - t[a] >= MIN_STOP_S:
                out.append((a, b))
            first = False
    return out


@dataclass(frozen=True)
class Replayed:
    """One drive of a built fleet's vehicle: its columns, the true bias, and each generation's
    rate and applied bias."""

    cols: dict[str, np.ndarray]
    true_bias: np.ndarray
    before: tuple[np.ndarray, np.ndarray]
    after: tuple[np.ndarray, np.ndarray]


def replayed(folder: Path, seed: int, index: int) -> Iterator[Replayed]:
    """Vehicle ``index``'s drives in a built fleet, through its baseline set and its new one."""
    truth, _ = simulate_vehicle(index, 1, seed)
    base = coefficient_file.load(folder / "fleet" / "sets" / f"{truth.sensor_id}.yaml")
    proposed = folder / "new" / f"{truth.sensor_id}-z.yaml"
    new = coefficient_file.load(proposed) if proposed.exists() else base
    for path in sorted((folder / "fleet" / "drives" / truth.vehicle_id).glob("drive-*.csv")):
        true_bias = drive_for(truth, index, int(path.stem.split("-")[1]), seed).bias_dps
        parts = list(blocks(path))
        cols = {k: np.concatenate([p[k] for p in parts]) for k in parts[0]}
        yield Replayed(cols, true_bias, _through(base, cols), _through(new, cols))


def wrong_slope(folders: list[Path]) -> Iterator[tuple[Path, int, int, str]]:
    """The built fleets' replayed vehicles whose sensor's table slope is wrong: folder, seed,
    vehicle index and sensor."""
    for folder in folders:
        seed = int(folder.name.split("-")[1])
        truth = {r["sensor_id"]: r for r in csv.DictReader((folder / "fleet" / "truth.csv").open())}
        for vehicle in sorted((folder / "fleet" / "drives").iterdir()):
            index = int(vehicle.name.split("-")[1])
            sensor = simulate_vehicle(index, 1, seed)[0].sensor_id
            if abs(float(truth[sensor]["slope_dps_per_c"])) > WRONG_SLOPE:
                yield folder, seed, index, sensor


def stops(folder: Path, seed: int, index: int) -> list[Stop]:
    """Every judged standstill of vehicle ``index``'s drives in a built fleet."""
    out = []
    for drive in replayed(folder, seed, index):
        cols, true_bias, (rb, bb), (ra, ba) = drive.cols, drive.true_bias, drive.before, drive.after
        for a, b in _runs(cols):
            err = rb[a:b] - cols["true_rate_dps"][a:b]
            term = float((ra[a:b] - rb[a:b]).mean())
            seconds = err[: (b - a) // 100 * 100].reshape(-1, 100).mean(axis=1)
            mean, bias = float(err.mean()), float(true_bias[a:b].mean())
            noise_var = float(np.var(seconds, ddof=1) / len(seconds))
            out.append(Stop(mean - bb[a], mean + term - ba[a], bias - bb[a], bias + term - ba[a],
                            float((err - true_bias[a:b]).mean()), noise_var))
    return out


def _rms(values: list[float]) -> float:
    return math.sqrt(sum(v * v for v in values) / len(values))


def _less_noise(values: list[float], noise_var: list[float]) -> float:
    """RMS of ``values`` less their own noise in quadrature; 0 when the noise is all of it."""
    return math.sqrt(max(sum(v * v - n for v, n in zip(values, noise_var, strict=True)) / len(values), 0.0))


def _noise_ratio(got: list[Stop]) -> str:
    var = [s.noise_var for s in got]
    after = _less_noise([s.after for s in got], var)
    return f"{_less_noise([s.before for s in got], var) / after:.1f}x" if after > 0 else "after: all noise"


def main(folders: list[Path]) -> None:
    print("| fleet | sensor | carried before -> after, ratio | truth: ratio | standstill noise RMS | "
          "less own noise: ratio |")
    print("|---|---|---|---|---|---|")
    for folder, seed, index, sensor in wrong_slope(folders):
        got = stops(folder, seed, index)
        before, after = _rms([s.before for s in got]), _rms([s.after for s in got])
        print(f"| {folder.name} | {sensor} | {before:.4f} -> {after:.4f}, {before / after:.1f}x | "
              f"{_rms([s.truth_before for s in got]) / _rms([s.truth_after for s in got]):.1f}x | "
              f"{_rms([s.noise for s in got]):.4f} | {_noise_ratio(got)} |", flush=True)


if __name__ == "__main__":
    main([Path(a) for a in sys.argv[1:]])
