"""New sets from the fleet's evidence: the set a sensor has, plus the temperature term its field
standstills learned (``fleet analyse --propose-sets``).

Why a ``channel``/``offset`` term in bias form on ``temp_c``: the field slope *s* is the bias's
temperature slope the set leaves over (deg/s/°C at 25 °C), and that term is a bias linear in the
temperature that the corrector, the daemon and ``apply`` already run (and the C evaluator): the
new set needs nothing new on the vehicle. The term acts on the raw output before the rate model,
so its coefficient is *s* divided by the model's slope at zero rate (raw units per °C); a set that
already has such a term on ``temp_c`` at 25 °C gets its coefficient changed, not a second term.

Why only significant evidence: a sensor whose field slope lies within :data:`SIGNIFICANCE`
standard errors of zero (or that has too little evidence) keeps its set untouched, so a proposal
never moves a good sensor by the noise of its estimate. The evidence and the before/after (the
standstills' 1σ within power-ons, before and after the term, on the same records) go into the new
set's ``fit.field_evidence`` and into ``proposals.md``.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path

import numpy as np

from canical.errors import CanicalError
from canical.fleet.analysis import REFERENCE_C, TOO_LITTLE, PowerOnSums, SensorVerdict
from canical.models.piecewise import PiecewisePoly
from canical.sets import signed_file
from canical.sets.coefficients import CoefficientSet
from canical.sets.term_kinds import CHANNEL, CHANNEL_OFFSET
from canical.sets.terms import Term

#: A field slope this many standard errors from zero is evidence enough to change a set.
SIGNIFICANCE = 3.0
TEMP_CHANNEL = "temp_c"
UNCHANGED, PROPOSED = "unchanged", "proposed"


@dataclass(frozen=True)
class SetSource:
    """A set file given with ``--propose-sets``: where it is, the set, and whether it was signed."""

    path: Path
    cset: CoefficientSet
    signed: bool


@dataclass(frozen=True)
class Evidence:
    """What the field says of one sensor axis: its slope, and the standstills' 1σ within power-ons
    before and after removing that slope (the same records)."""

    slope_dps_per_c: float
    slope_se: float
    records: int
    power_ons: int
    vehicles: int
    before_dps: float
    after_dps: float


@dataclass(frozen=True)
class Proposal:
    """One sensor axis's outcome: a new set (``PROPOSED``) or its set left as it is, and why."""

    sensor_id: str
    axis: str
    outcome: str
    reason: str
    source: SetSource | None
    evidence: Evidence | None
    new_set: CoefficientSet | None = None
    coefficient_raw_per_c: float = math.nan


def read_sets(root: Path, note: Callable[[str], None]) -> dict[tuple[str, str], SetSource]:
    """The single-axis sets in a folder (``*.yaml``, ``*.yml``, recursively) or one set file, by
    (sensor id, axis). An IMU set is skipped with a line; two files for one axis is an error."""
    if root.is_dir():
        paths = sorted(p for p in root.rglob("*") if p.suffix in (".yaml", ".yml") and p.is_file())
    elif root.is_file():
        paths = [root]
    else:
        raise CanicalError(f"--propose-sets {root}: no such set file or folder")
    found: dict[tuple[str, str], SetSource] = {}
    for path in paths:
        read = signed_file.read_set_file(path)
        if read.single is None:
            note(f"{path}: an IMU set, skipped (--propose-sets takes single-axis sets)")
            continue
        key = (read.single.sensor_id, read.single.axis)
        if key in found:
            raise CanicalError(f"{path}: a second set for sensor {key[0]} axis {key[1]} "
                               f"(the first is {found[key].path})")
        found[key] = SetSource(path, read.single, read.signed.record is not None)
    if not found:
        raise CanicalError(f"--propose-sets {root}: no single-axis set files (*.yaml)")
    return found


@dataclass(frozen=True)
class Within:
    """One sensor axis's adopted standstills, pooled within power-ons (each power-on's means
    removed): degrees of freedom and the centred sums of squares and products of temperature ``t``,
    hours since power-on ``h`` and bias ``b``."""

    dof: int
    tt: float
    th: float
    hh: float
    tb: float
    hb: float
    bb: float

    def sigma(self, slope: float) -> float:
        """The 1σ of the biases less ``slope``·t, after the best drift within power-ons (the same
        drift fitted before and after, so the difference is the temperature term's alone)."""
        rr = self.bb - 2 * slope * self.tb + slope * slope * self.tt
        hr = self.hb - slope * self.th
        rss = rr - hr * hr / self.hh if self.hh > 0 else rr
        return math.sqrt(max(rss, 0.0) / max(self.dof - 1, 1))


def within_sums(sums: PowerOnSums) -> dict[tuple[str, str], Within]:
    """Per sensor axis, its :class:`Within` from the per-power-on sums."""
    n, st, sh, sb, stt, sth, shh, stb, shb, sbb = sums.sums.T
    centred = np.column_stack([stt - st * st / n, sth - st * sh / n, shh - sh * sh / n,
                               stb - st * sb / n, shb - sh * sb / n, sbb - sb * sb / n])
    out: dict[tuple[str, str], Within] = {}
    for i, key in enumerate(zip(sums.sensor_id.tolist(), sums.axis.tolist(), strict=True)):
        prev = out.get(key, Within(0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0))
        add = [float(x) for x in centred[i]]
        out[key] = Within(prev.dof + int(n[i]) - 1, prev.tt + add[0], prev.th + add[1], prev.hh + add[2],
                          prev.tb + add[3], prev.hb + add[4], prev.bb + add[5])
    return out


def evidence_of(verdict: SensorVerdict, within: Within) -> Evidence:
    """The verdict's slope with the 1σ of the standstills within power-ons before and after it."""
    s = verdict.slope_dps_per_c
    return Evidence(s, verdict.slope_se, verdict.records, verdict.power_ons, verdict.vehicles,
                    within.sigma(0.0), within.sigma(s if math.isfinite(s) else 0.0))


def significant(verdict: SensorVerdict) -> bool:
    s, se = verdict.slope_dps_per_c, verdict.slope_se
    return (verdict.verdict != TOO_LITTLE and math.isfinite(s) and math.isfinite(se)
            and abs(s) > SIGNIFICANCE * se)


def propose(verdicts: Sequence[SensorVerdict], sums: PowerOnSums,
            sets: Mapping[tuple[str, str], SetSource], dataset: str) -> list[Proposal]:
    """Every sensor axis of the analysis, and every set given: a new set or unchanged, and why."""
    within = within_sums(sums)
    out = [_one(v, sets.get((v.sensor_id, v.axis)), within.get((v.sensor_id, v.axis)), dataset)
           for v in verdicts]
    seen = {(v.sensor_id, v.axis) for v in verdicts}
    out += [Proposal(k[0], k[1], UNCHANGED, "no field records", src, None)
            for k, src in sorted(sets.items()) if k not in seen]
    return out


def _one(verdict: SensorVerdict, source: SetSource | None,
         within: Within | None, dataset: str) -> Proposal:
    evidence = evidence_of(verdict, within) if within is not None else None
    key = (verdict.sensor_id, verdict.axis)
    if not significant(verdict):
        why = (TOO_LITTLE if verdict.verdict == TOO_LITTLE else
               "no temperature recorded" if not math.isfinite(verdict.slope_dps_per_c) else
               f"field slope within {SIGNIFICANCE:g} standard errors of the set's")
        return Proposal(*key, UNCHANGED, why, source, evidence)
    if source is None:
        return Proposal(*key, UNCHANGED, "significant field slope, but no set given for it", None, evidence)
    if not source.cset.kind.piecewise:
        return Proposal(*key, UNCHANGED, "its set's model (forward) takes no effect terms", source, evidence)
    assert evidence is not None
    new_set, coefficient = with_field_term(source.cset, evidence, dataset)
    return Proposal(*key, PROPOSED, "field slope significant", source, evidence, new_set, coefficient)


def with_field_term(cset: CoefficientSet, evidence: Evidence, dataset: str) -> tuple[CoefficientSet, float]:
    """The set plus the field-learned temperature term, with its evidence in ``fit``; and the
    coefficient added (raw units per °C)."""
    model = cset.rate_model()
    if not isinstance(model, PiecewisePoly):
        raise CanicalError(f"sensor {cset.sensor_id}: a forward model takes no effect terms")
    gain = float(model.slope(np.array([0.0]))[0])  # deg/s per raw unit at rest
    if not math.isfinite(gain) or gain == 0.0:
        raise CanicalError(f"sensor {cset.sensor_id}: the set's model has no slope at rest")
    added = evidence.slope_dps_per_c / gain
    terms, merged = [], False
    for term in cset.terms:
        if not merged and _is_field_term(term):
            term, merged = dataclasses.replace(term, coefficient=term.coefficient + added), True
        terms.append(term)
    if not merged:
        terms.append(Term.of(CHANNEL_OFFSET, "bias", added, channel=TEMP_CHANNEL, reference=REFERENCE_C))
    fit = {**cset.fit, "field_evidence": _fit_record(evidence, added, dataset)}
    stamp = datetime.now(UTC).strftime("%Y-%m-%dT%H:%M:%SZ")
    return dataclasses.replace(cset, terms=tuple(terms), fit=fit, created=stamp), added


def _is_field_term(term: Term) -> bool:
    return (term.kind, term.feature, term.form, term.channel, float(term.reference)) == \
        (CHANNEL, "offset", "bias", TEMP_CHANNEL, REFERENCE_C)


def _fit_record(evidence: Evidence, added: float, dataset: str) -> dict[str, object]:
    return {"dataset": dataset, "slope_dps_per_c": evidence.slope_dps_per_c, "slope_se": evidence.slope_se,
            "records": evidence.records, "power_ons": evidence.power_ons, "vehicles": evidence.vehicles,
            "coefficient_added": added, "within_sigma_before_dps": evidence.before_dps,
            "within_sigma_after_dps": evidence.after_dps}

