"""Per sensor, what the fleet's standstills say: turn-on spread, slope left by the set, drift, verdict.

Why in two steps: a sensor's evidence is its standstills grouped by power-on (the turn-on bias
is new at each). Step one (:func:`summarise`, per vehicle, where the records are) reduces each
power-on to a few sums; step two (:func:`judge`) combines a sensor's power-ons. The sums are
all the model needs, so the engine moves kilobytes, not records, and any split of the vehicles
over workers gives the same sums and the same verdicts.

The model of an adopted standstill's bias ``b`` at temperature ``T`` and time ``t`` since
power-on ``g``: ``b = o_g + s·(T − 25) + d·t/3600 + e``. The slope ``s`` the set leaves over and
the drift ``d`` within power-ons come from the deviations from each power-on's means (the
turn-on offsets ``o_g`` drop out), with standard errors from the residuals. Each offset ``o_g``
is then regressed on the operating hours at that power-on: the slope is the drift with hours,
the residuals' spread the turn-on spread.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np
import pyarrow as pa

REFERENCE_C = 25.0
#: The spec: a turn-on spread (1σ) beyond this, or a slope beyond :data:`SLOPE_LIMIT` by more than
#: two standard errors, is out of spec; a drift beyond :data:`DRIFT_LIMIT` and four standard errors
#: is drifting.
SPREAD_LIMIT = 0.5  # deg/s
SLOPE_LIMIT = 0.01  # deg/s/°C
DRIFT_LIMIT = 0.003  # deg/s per operating hour
MIN_RECORDS, MIN_POWER_ONS = 10, 3
IN_SPEC, DRIFTING, OUT_OF_SPEC, TOO_LITTLE = "in spec", "drifting", "out of spec", "too little evidence"
_SUMS = ("n", "st", "sh", "sb", "stt", "sth", "shh", "stb", "shb", "sbb")


@dataclass(frozen=True)
class PowerOnSums:
    """Per (sensor, axis, vehicle, power-on): the count and sums of its adopted standstills'
    temperature deviation ``t`` (°C from 25), time ``h`` (hours since power-on) and bias ``b``,
    and the vehicle's operating hours when it began. Columns of equal length."""

    sensor_id: np.ndarray
    axis: np.ndarray
    vehicle_id: np.ndarray
    power_on: np.ndarray
    hours_before: np.ndarray
    sums: np.ndarray  # (rows, len(_SUMS)), in _SUMS's order
    set_id: np.ndarray  # the set id of the power-on's last standstill (its calibration generation)

    @staticmethod
    def concat(parts: Sequence[PowerOnSums]) -> PowerOnSums:
        """Several vehicles' sums as one, ordered by sensor, axis, vehicle and power-on."""
        if not parts:
            empty = np.array([], dtype=object)
            return PowerOnSums(empty, empty, empty, np.array([], dtype=np.int64), np.array([]),
                               np.zeros((0, len(_SUMS))), np.array([], dtype=np.int64))
        joined = [np.concatenate([getattr(p, f) for p in parts]) for f in
                  ("sensor_id", "axis", "vehicle_id", "power_on", "hours_before", "sums", "set_id")]
        order = np.lexsort((joined[3], joined[2].astype(str), joined[1].astype(str), joined[0].astype(str)))
        return PowerOnSums(*(c[order] for c in joined))


@dataclass(frozen=True)
class SensorVerdict:
    """One sensor axis, judged: what ``sensors.csv`` holds."""

    sensor_id: str
    axis: str
    verdict: str
    slope_dps_per_c: float  # the temperature slope the set leaves over (NaN: no temperature)
    slope_se: float
    spread_dps: float  # turn-on bias spread, 1σ, after the drift with hours
    drift_dps_per_h: float  # per operating hour, across power-ons
    drift_se: float
    records: int  # adopted standstills
    power_ons: int
    vehicles: int
    hours: float  # operating hours spanned
    set_id: int  # the set id of its last power-on: the calibration generation it runs now


def summarise(table: pa.Table) -> PowerOnSums:
    """One vehicle's (or several vehicles') rows as sums per power-on (rows in any order)."""
    cols = {name: table.column(name).to_numpy(zero_copy_only=False) for name in
            ("vehicle_id", "sensor_id", "axis", "power_on", "since_power_on_s", "temp_c", "bias_dps",
             "decision", "record_id", "set_id")}
    hours = _hours_before(cols["vehicle_id"], cols["power_on"], cols["since_power_on_s"])
    keep = _kept(cols)
    order = np.lexsort((cols["record_id"][keep].astype(str), cols["axis"][keep].astype(str),
                        cols["power_on"][keep], cols["sensor_id"][keep].astype(str),
                        cols["vehicle_id"][keep].astype(str)))
    pick = {k: v[keep][order] for k, v in cols.items()}
    temp = pick["temp_c"].astype(float)
    t = np.where(np.isfinite(temp), temp - REFERENCE_C, 0.0)  # none recorded: no slope, the rest holds
    h = pick["since_power_on_s"].astype(float) / 3600.0
    b = pick["bias_dps"].astype(float)
    terms = np.column_stack([np.ones_like(t), t, h, b, t * t, t * h, h * h, t * b, h * b, b * b])
    keys = list(zip(pick["sensor_id"], pick["axis"], pick["vehicle_id"], pick["power_on"], strict=True))
    starts = [i for i in range(len(keys)) if i == 0 or keys[i] != keys[i - 1]]
    sums = np.add.reduceat(terms, starts, axis=0) if starts else np.zeros((0, len(_SUMS)))
    first = [keys[i] for i in starts]
    last_rows = [*(i - 1 for i in starts[1:]), len(keys) - 1] if starts else []
    return PowerOnSums(np.array([k[0] for k in first], dtype=object),
                       np.array([k[1] for k in first], dtype=object),
                       np.array([k[2] for k in first], dtype=object),
                       np.array([k[3] for k in first], dtype=np.int64),
                       np.array([hours[(k[2], int(k[3]))] for k in first]), sums,
                       np.asarray(pick["set_id"][last_rows], dtype=np.int64))


def _kept(cols: dict[str, np.ndarray]) -> np.ndarray:
    """The adopted standstills to learn from: those with a temperature, or, for a sensor axis that
    never recorded one (no temperature input), all of them."""
    adopted = cols["decision"] == "adopted"
    measured = np.isfinite(cols["temp_c"].astype(float))
    pairs = list(zip(cols["sensor_id"].tolist(), cols["axis"].tolist(), strict=True))
    with_temp = {p for p, m, a in zip(pairs, measured.tolist(), adopted.tolist(), strict=True) if m and a}
    never = np.array([p not in with_temp for p in pairs], dtype=bool)
    kept: np.ndarray = adopted & (measured | never)
    return kept


def _hours_before(vehicle: np.ndarray, power_on: np.ndarray,
                  since: np.ndarray) -> dict[tuple[str, int], float]:
    """Per (vehicle, power-on): operating hours before it, from each earlier power-on's last record."""
    last: dict[tuple[str, int], float] = {}
    for v, p, s in zip(vehicle.tolist(), power_on.tolist(), since.tolist(), strict=True):
        key = (v, int(p))
        last[key] = max(last.get(key, 0.0), float(s))
    out: dict[tuple[str, int], float] = {}
    running: dict[str, float] = {}
    for v, p in sorted(last):
        out[(v, p)] = running.get(v, 0.0)
        running[v] = running.get(v, 0.0) + last[(v, p)] / 3600.0
    return out


def judge(sums: PowerOnSums) -> list[SensorVerdict]:
    """Every sensor axis's verdict from its power-ons' sums (``sums`` ordered as :meth:`concat` orders)."""
    keys = list(zip(sums.sensor_id.tolist(), sums.axis.tolist(), strict=True))
    starts = [i for i in range(len(keys)) if i == 0 or keys[i] != keys[i - 1]] + [len(keys)]
    return [dataclasses.replace(_judge_one(keys[a], sums.sums[a:b], sums.hours_before[a:b],
                                           sums.vehicle_id[a:b]), set_id=int(sums.set_id[b - 1]))
            for a, b in itertools.pairwise(starts)]


def _judge_one(key: tuple[str, str], s: np.ndarray, hours_before: np.ndarray,
               vehicles: np.ndarray) -> SensorVerdict:
    n, st, sh, sb, stt, sth, shh, stb, shb, sbb = s.T
    # within power-on deviations: sums of centred cross-products, pooled over power-ons
    ctt, cth, chh = (stt - st * st / n).sum(), (sth - st * sh / n).sum(), (shh - sh * sh / n).sum()
    ctb, chb, cbb = (stb - st * sb / n).sum(), (shb - sh * sb / n).sum(), (sbb - sb * sb / n).sum()
    records, groups = int(n.sum()), len(n)
    slope = slope_se = math.nan
    within = np.array([[ctt, cth], [cth, chh]])
    dof = records - groups - 2
    if dof > 0 and np.linalg.det(within) > 1e-12 * max(ctt * chh, 1e-300):
        beta = np.linalg.solve(within, np.array([ctb, chb]))
        rss = max(cbb - beta @ np.array([ctb, chb]), 0.0)
        cov = rss / dof * np.linalg.inv(within)
        slope, slope_se = float(beta[0]), float(math.sqrt(cov[0, 0]))
    offsets = (sb - (slope if math.isfinite(slope) else 0.0) * st) / n
    hours = hours_before + sh / n
    drift, drift_se, spread = _drift_and_spread(offsets, hours)
    verdict = _verdict(records, groups, slope, slope_se, drift, drift_se, spread)
    return SensorVerdict(key[0], key[1], verdict, slope, slope_se, spread, drift, drift_se, records, groups,
                         len(set(vehicles.tolist())), float(hours.max() - hours.min()) if groups else 0.0, 0)


def _drift_and_spread(offsets: np.ndarray, hours: np.ndarray) -> tuple[float, float, float]:
    """The offsets' line against operating hours (slope, its SE) and the residuals' 1σ."""
    g = len(offsets)
    if g < 2:
        return math.nan, math.nan, math.nan
    hc = hours - hours.mean()
    shh = float(hc @ hc)
    if g < 3 or shh <= 0:
        return math.nan, math.nan, float(np.std(offsets, ddof=1))
    drift = float(hc @ (offsets - offsets.mean()) / shh)
    resid = offsets - offsets.mean() - drift * hc
    sigma2 = float(resid @ resid) / (g - 2)
    return drift, math.sqrt(sigma2 / shh), math.sqrt(sigma2)


def _verdict(records: int, groups: int, slope: float, slope_se: float, drift: float, drift_se: float,
             spread: float) -> str:
    if records < MIN_RECORDS or groups < MIN_POWER_ONS:
        return TOO_LITTLE
    if spread > SPREAD_LIMIT or (math.isfinite(slope) and abs(slope) - 2 * slope_se > SLOPE_LIMIT):
        return OUT_OF_SPEC
    if math.isfinite(drift) and abs(drift) > DRIFT_LIMIT and abs(drift) > 4 * drift_se:
        return DRIFTING
    return IN_SPEC
