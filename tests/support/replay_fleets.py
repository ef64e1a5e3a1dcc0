"""Simulated fleets replayed before and after their proposed sets: the issue's bar on the
zero-rate error, judged on the sensors whose table slope was wrong and on the others.

Why drives for a few vehicles only: a sensor's proposal depends on its own field log alone, and
the wrong-slope sensors are about 1 % of a fleet; so the whole fleet's field log is simulated,
ingested and analysed (as a user runs it), but raw drives are written only for the wrong-slope
vehicles and a few others, which keeps a fleet of a hundred vehicles to seconds of replay.
"""

from __future__ import annotations

import argparse
import contextlib
import csv
import dataclasses
import io
import math
from dataclasses import dataclass
from pathlib import Path

from canical.commands.cli import main
from canical.commands.simulate_fleet import write_drives
from canical.sets import coefficient_file
from canical.sim.fleet import simulate_vehicle

SET = Path(__file__).resolve().parents[1] / "data" / "sets" / "daemon-z.yaml"
#: A table slope is wrong when the sensor leaves more than the spec over its set (deg/s/°C).
WRONG_SLOPE = 0.01
DAYS = 20


@dataclass(frozen=True)
class FleetSpec:
    seed: int
    vehicles: int
    drives: int  # per replayed vehicle
    others: int = 2  # vehicles replayed beside the wrong-slope ones (the first that are not)


#: Fleets drawn for issue 35's per-sensor bar (the first 20 seeds from 1000 holding a wrong-slope
#: sensor, 20-100 vehicles, 1-3 drives; ``support/sets_fleets.py`` runs them): judged beside the
#: explored ones, so nothing is tuned to a few seeds, without running the blind ones.
DRAWN = [FleetSpec(1001, 93, 2), FleetSpec(1002, 68, 2), FleetSpec(1003, 44, 1), FleetSpec(1005, 54, 1),
         FleetSpec(1008, 48, 1), FleetSpec(1010, 76, 1), FleetSpec(1011, 43, 1), FleetSpec(1012, 80, 1),
         FleetSpec(1013, 31, 3), FleetSpec(1014, 68, 2), FleetSpec(1016, 71, 1), FleetSpec(1017, 99, 3),
         FleetSpec(1019, 47, 1), FleetSpec(1020, 89, 2), FleetSpec(1025, 79, 3), FleetSpec(1026, 70, 1),
         FleetSpec(1030, 49, 1), FleetSpec(1031, 92, 3), FleetSpec(1033, 68, 3), FleetSpec(1036, 50, 1)]


#: Fleets drawn for the noise-removed figure (issue 35's floor): the first 10 seeds from 2001 holding
#: a wrong-slope sensor, sizes and drives drawn with ``numpy.random.default_rng(2026)``, a draw per
#: seed tried; never looked at before the figure was written.
FRESH = [FleetSpec(2003, 49, 2), FleetSpec(2006, 87, 3), FleetSpec(2008, 78, 1), FleetSpec(2009, 89, 2),
         FleetSpec(2011, 33, 3), FleetSpec(2024, 87, 1), FleetSpec(2026, 100, 2), FleetSpec(2029, 46, 2),
         FleetSpec(2031, 98, 1), FleetSpec(2032, 95, 3)]


@dataclass(frozen=True)
class LessNoise:
    """The carried figure less the standstills' own noise over a group: its sums before and after
    (unbiased, unfloored), and per sensor before / after, and the same with the after at its +1σ
    bound (a sensor whose after is all noise has no point ratio, only that bound's)."""

    before_sq: float = 0.0
    after_sq: float = 0.0
    per_sensor: tuple[float, ...] = ()
    per_sensor_bound: tuple[float, ...] = ()

    def plus(self, other: LessNoise) -> LessNoise:
        return LessNoise(self.before_sq + other.before_sq, self.after_sq + other.after_sq,
                         self.per_sensor + other.per_sensor, self.per_sensor_bound + other.per_sensor_bound)


@dataclass(frozen=True)
class Pooled:
    """RMS over the standstills of a group of vehicles, before and after (carried into stops),
    and each sensor's own ratio (before/after for the wrong ones, after/before for the others);
    the same less the standstills' own noise."""

    stops: int
    before_sq: float
    after_sq: float
    per_sensor: tuple[float, ...]
    less_noise: LessNoise = LessNoise()

    @property
    def sensors(self) -> int:
        return len(self.per_sensor)

    def rms(self) -> tuple[float, float]:
        """Before and after, RMS over the group's standstills."""
        if not self.stops:
            return math.nan, math.nan
        return math.sqrt(self.before_sq / self.stops), math.sqrt(self.after_sq / self.stops)

    def less_noise_rms(self) -> tuple[float, float]:
        """Before and after less the standstills' own noise, RMS (floored at 0 here, reported)."""
        if not self.stops:
            return math.nan, math.nan
        return (math.sqrt(max(self.less_noise.before_sq, 0.0) / self.stops),
                math.sqrt(max(self.less_noise.after_sq, 0.0) / self.stops))


@dataclass(frozen=True)
class FleetRatio:
    spec: FleetSpec
    wrong: Pooled
    others: Pooled
    unchanged_same: bool  # the sensors without a new set replayed the same figures


def quiet(argv: list[str]) -> None:
    with contextlib.redirect_stdout(io.StringIO()):
        assert main(argv) == 0, argv


def build(root: Path, spec: FleetSpec) -> None:
    """The fleet's field logs and sets; drives for the wrong-slope vehicles and ``others`` more;
    ingested, analysed with --propose-sets, replayed into ``root/replay.csv``."""
    quiet(["simulate", "fleet", "--vehicles", str(spec.vehicles), "--days", str(DAYS), "--seed",
           str(spec.seed), "-o", str(root / "fleet")])
    template = coefficient_file.load(SET)
    (root / "fleet" / "sets").mkdir()
    args = argparse.Namespace(drives=spec.drives, seed=spec.seed)
    others = 0
    for index in range(spec.vehicles):
        truth, _ = simulate_vehicle(index, 1, spec.seed)
        wrong = abs(truth.slope_dps_per_c) > WRONG_SLOPE
        if wrong or others < spec.others:
            others += not wrong
            write_drives(root / "fleet", truth, index, args, template)
        else:
            coefficient_file.save(root / "fleet" / "sets" / f"{truth.sensor_id}.yaml",
                                  dataclasses.replace(template, sensor_id=truth.sensor_id))
    quiet(["fleet", "ingest", str(root / "fleet"), "-o", str(root / "dataset")])
    quiet(["fleet", "analyse", str(root / "dataset"), "--report-dir", str(root / "report"),
           "--propose-sets", str(root / "fleet" / "sets"), "-o", str(root / "new")])
    replay(root)


def replay(root: Path) -> None:
    """A built fleet's drives replayed into ``root/replay.csv`` (again: after a change to the replay)."""
    quiet(["fleet", "replay", str(root / "fleet" / "drives"), "--sets", str(root / "new"),
           "--baseline", str(root / "fleet" / "sets"), "-o", str(root / "replay.csv")])


def judge(root: Path, spec: FleetSpec) -> FleetRatio:
    """The replayed vehicles split by the truth: wrong slope or not; pooled before and after."""
    truth = {r["sensor_id"]: r for r in csv.DictReader((root / "fleet" / "truth.csv").open())}
    got = list(csv.DictReader((root / "replay.csv").open()))
    proposed = {r["sensor_id"] for r in csv.DictReader((root / "new" / "proposals.csv").open())
                if r["outcome"] == "proposed"}
    wrong = [r for r in got if abs(float(truth[r["sensor_id"]]["slope_dps_per_c"])) > WRONG_SLOPE]
    others = [r for r in got if r not in wrong]
    same = all(r["carried_before_dps"] == r["carried_after_dps"] for r in others
               if r["sensor_id"] not in proposed)
    return FleetRatio(spec, pool(wrong, ratio=True), pool(others, ratio=False), same)


def pool(rows: list[dict[str, str]], *, ratio: bool) -> Pooled:
    stops = [int(r["standstills"]) for r in rows]
    before = [float(r["carried_before_dps"]) for r in rows]
    after = [float(r["carried_after_dps"]) for r in rows]
    per = tuple(b / a if ratio else a / b for b, a in zip(before, after, strict=True))
    return Pooled(sum(stops), sum(n * b * b for n, b in zip(stops, before, strict=True)),
                  sum(n * a * a for n, a in zip(stops, after, strict=True)), per,
                  summed([less_noise(r) for r in rows]))


def less_noise(row: dict[str, str]) -> LessNoise:
    """One vehicle's figures less its standstills' own noise (its sums from replay.csv's RMS)."""
    n = int(row["standstills"])
    sums = [n * (float(row[f"carried_{w}_dps"]) ** 2 - float(row[f"carried_noise_{w}_dps"]) ** 2)
            for w in ("before", "after")]
    before, after = (float(row[f"carried_less_noise_{w}_dps"]) for w in ("before", "after"))
    bound = after + float(row["carried_less_noise_after_sd_dps"])
    return LessNoise(sums[0], sums[1], (before / after if after else math.inf,), (before / bound,))


def summed(parts: list[LessNoise]) -> LessNoise:
    total = LessNoise()
    for part in parts:
        total = total.plus(part)
    return total


def combined(groups: list[Pooled]) -> Pooled:
    """Several fleets' groups as one: their standstills pooled."""
    return Pooled(sum(g.stops for g in groups), sum(g.before_sq for g in groups),
                  sum(g.after_sq for g in groups), tuple(x for g in groups for x in g.per_sensor),
                  summed([g.less_noise for g in groups]))
