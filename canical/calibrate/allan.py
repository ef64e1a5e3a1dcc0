"""Allan deviation of a gyro's rate output and the IEEE Std 952 noise terms read from it.

Why: a gyro's noise is not one number. Its Allan deviation σ(τ) (the spread of the
difference of successive τ-averages) separates the terms by their slope on a log-log plot:
angle random walk (white rate noise) falls as τ^−1/2, bias instability (flicker) is flat,
rate random walk rises as τ^+1/2. IEEE Std 952 reads each from a line of that slope laid
against the curve: ARW = σ of the −1/2 line at τ = 1 s, BI = σ_min / 0.664 (0.664 =
√(2 ln 2 / π), the flat level of flicker noise), RRW = σ of the +1/2 line at τ = 3 s.

The deviation itself comes from allantools (overlapping ADEV); several records (the
zero-rate plateaus of a turntable session, or a static record cut at lost rows) are pooled
per cluster size, each record's overlapping estimate weighted by its number of terms.

The three lines are laid against the curve at once: Allan variances of the terms add,
σ²(τ) = N²/τ + (0.664·B)² + K²τ/3, fitted with non-negative N², B², K² and each point weighted
by its own error, so each line's level is set where its term dominates and is not pulled up
by the others. A term is *resolved* only when it dominates the fitted curve over a stretch
of τ (a factor of 3); otherwise it is reported "not resolved" with the upper bound the data
gives (its line laid under the curve). The curve's own minimum / 0.664, the classic graphical
BI read-out, is reported beside the fitted one.

Confidence follows IEEE Std 952 annex C: σ(τ) from K independent (non-overlapping) clusters
has a relative error of 1/√(2(K−1)). A term's interval is ±2 of that error at the most
precise τ where it dominates, divided by its share of the variance there. Over many seeds of
synthetic noise (tests/benchmarks/bench_allan.py) such intervals hold the true value in 80–95%
of seeds, ARW beside a flicker floor in half: the estimates at neighbouring τ are correlated
and the terms share the curve, so no finer confidence is claimed.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

SQRT_HOUR = 60.0  # √(3600 s)
FLICKER_FLOOR = 0.664  # σ_min = 0.664·B for flicker (1/f) rate noise
RRW_TAU_S = 3.0
POINTS_PER_DECADE = 8
MIN_CLUSTERS = 3  # the longest τ still has this many independent clusters


@dataclass(frozen=True)
class AllanCurve:
    """Pooled overlapping Allan deviation of one or more records sampled at one rate."""

    tau_s: np.ndarray
    adev: np.ndarray  # in the records' unit (deg/s)
    clusters: np.ndarray  # independent clusters of length τ, summed over the records
    sample_rate_hz: float
    records: int
    duration_s: float  # summed over the records

    @property
    def rel_error(self) -> np.ndarray:
        """IEEE 952 annex C: relative 1σ error of σ(τ) from K independent clusters."""
        rel: np.ndarray = 1.0 / np.sqrt(2.0 * np.maximum(self.clusters - 1, 1))
        return rel


@dataclass(frozen=True)
class NoiseTerm:
    """One read-out: value with its ~68% interval, or not resolved with an upper bound."""

    name: str
    unit: str
    resolved: bool
    value: float  # the read-out; when not resolved, the upper bound
    low: float
    high: float
    tau_s: float  # where the line touches the curve
    clusters: int
    note: str

    def to_dict(self) -> dict[str, Any]:
        return {
            "name": self.name,
            "unit": self.unit,
            "resolved": self.resolved,
            "value": self.value if self.resolved else None,
            "interval": [self.low, self.high] if self.resolved else None,
            "upper_bound": None if self.resolved else self.value,
            "tau_s": self.tau_s,
            "clusters": self.clusters,
            "note": self.note,
        }


OADEV_BLOCK = 1 << 15  # samples of a second difference squared and summed at a time (in the cache)


def allan_deviation(
    records: Sequence[np.ndarray], sample_rate_hz: float, *, points_per_decade: int = POINTS_PER_DECADE
) -> AllanCurve:
    """Overlapping ADEV of rate records (same sample rate), pooled per cluster size.

    τ runs from one sample to the longest τ at which the longest record still has
    ``MIN_CLUSTERS`` independent clusters, log-spaced.
    """
    recs = [np.asarray(r, dtype=float) for r in records if len(r) >= 2 * MIN_CLUSTERS]
    if not recs:
        raise ValueError(f"no record of at least {2 * MIN_CLUSTERS} samples")
    longest = max(len(r) for r in recs)
    top = max(longest // MIN_CLUSTERS, 1)
    n_points = max(int(np.ceil(np.log10(top) * points_per_decade)) + 1, 1)
    m_grid = np.unique(np.round(np.logspace(0, np.log10(top), n_points)).astype(int))
    var_sum = np.zeros(m_grid.size)
    terms = np.zeros(m_grid.size)
    clusters = np.zeros(m_grid.size, dtype=np.int64)
    for r in recs:
        usable = m_grid[m_grid <= len(r) // 2]
        if usable.size == 0:
            continue
        m, devs, ns = overlapping_adev(r, sample_rate_hz, usable)
        idx = np.searchsorted(m_grid, m)
        var_sum[idx] += np.asarray(ns) * np.asarray(devs) ** 2
        terms[idx] += np.asarray(ns)
        clusters[idx] += len(r) // m_grid[idx]
    keep = (terms > 0) & (clusters >= 2)
    return AllanCurve(
        tau_s=m_grid[keep] / sample_rate_hz,
        adev=np.sqrt(var_sum[keep] / terms[keep]),
        clusters=clusters[keep],
        sample_rate_hz=float(sample_rate_hz),
        records=len(recs),
        duration_s=float(sum(len(r) for r in recs) / sample_rate_hz),
    )


def overlapping_adev(record: np.ndarray, sample_rate_hz: float,
                     m_values: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """allantools' ``oadev`` of a rate record at clusters of ``m_values`` samples: (m, ADEV, terms),
    clusters with fewer than two terms left out.

    Why here: allantools takes each second difference of the whole record's phase at once, several
    copies of a record of millions of samples (gigabytes for hours at 1 kHz). The phase is made in
    place and the squares summed a block at a time, small enough to stay in the processor's cache
    (a block's second difference made in one buffer, its squares summed by a dot product): the
    same operations on the same phase, the sums added in another order, so equal within rounding.
    A record that is not finite goes to allantools, which trims it.
    """
    if not np.isfinite(record).all():
        import allantools

        taus, devs, _errs, ns = allantools.oadev(record, rate=sample_rate_hz, data_type="freq",
                                                 taus=m_values / sample_rate_hz)
        m = np.round(np.asarray(taus) * sample_rate_hz).astype(int)
        return m, np.asarray(devs, dtype=float), np.asarray(ns, dtype=float)
    phase = np.empty(record.size + 1)
    phase[0] = 0.0
    np.subtract(record, np.mean(record), out=phase[1:])  # finite: nanmean's value, without its copy
    np.cumsum(phase[1:], out=phase[1:])
    phase[1:] *= 1.0 / float(sample_rate_hz)
    m_all = np.unique(np.asarray(m_values, dtype=int))
    m_all = m_all[(m_all > 0) & (m_all < phase.size)]
    n_all = np.maximum(phase.size - 2 * m_all, 1)
    totals = _second_difference_sums(phase, m_all, n_all)
    devs = np.sqrt(totals / (2.0 * n_all)) / m_all * sample_rate_hz
    ns = n_all.astype(float)
    keep = ns > 1
    return m_all[keep], devs[keep], ns[keep]


def _second_difference_sums(phase: np.ndarray, m_all: np.ndarray, n_all: np.ndarray) -> np.ndarray:
    """Σᵢ (phase[i+2m] − 2·phase[i+m] + phase[i])² over i < n, for each m and its n.

    Block by block, every cluster size in turn: a block of the phase is read from memory once
    for all sizes (it stays in the cache), the blocks m and 2m later once per size, a third
    less of what bounds the time. Each size's sum runs over the same blocks in the same order
    whatever the other sizes.
    """
    block = np.empty(OADEV_BLOCK)
    totals = np.zeros(m_all.size)
    sizes = list(enumerate(zip(m_all.tolist(), n_all.tolist(), strict=True)))
    for a in range(0, int(n_all.max(initial=0)), OADEV_BLOCK):
        for k, (m, n) in sizes:
            if a >= n:
                continue
            b = min(a + OADEV_BLOCK, n)
            v = block[: b - a]  # the second difference made in place
            np.multiply(phase[m + a : m + b], -2.0, out=v)
            v += phase[2 * m + a : 2 * m + b]
            v += phase[a:b]
            totals[k] += float(v @ v)
    return totals


# Allan variance of each IEEE 952 term is a power of τ: σ² = Σ A_p·τ^p, slopes −1/2, 0, +1/2 in σ.
# Quantisation (−1) and rate ramp (+1) are left out: free, they bend the fit along the random
# wiggles of the overlapping estimates (which are correlated across τ); where they are really
# there, the terms they touch are not resolved or are read high, never low.
POWERS = {"arw": -1.0, "bias_instability": 0.0, "rrw": 1.0}
DOMINANT_SHARE = 0.5  # a term is seen where it makes at least this share of the variance
MIN_SPAN = 3.0  # ... over τ spanning at least this factor: a line is not drawn through a bump
#: ... and is told from nothing by this many of its errors where it is known best: the curve's
#: tail has few clusters, and a wiggle there seen at two errors over a dozen τ is chance.
CLAIM_SIGMAS = 3.0
#: Rate random walk, the slow wander, must rise as τ^+1/2 over a decade of τ that reaches its
#: read-out τ (3 s): a rise over less, or only at shorter τ, is what a drift, a rate ramp or a
#: change of temperature makes in a short record as well.
RRW_MIN_SPAN = 10.0


def fit_terms(curve: AllanCurve) -> dict[str, float]:
    """Non-negative A_p of σ²(τ) = Σ A_p·τ^p, each point weighted by its relative error.

    The lines of slope −1/2, 0, +1/2 laid against the curve all at once: each line's level
    is set where its term dominates, not raised by the others.
    """
    avar = curve.adev**2
    scale = 1.0 / (avar * 2.0 * curve.rel_error)  # the relative error of σ² is twice that of σ
    design = np.column_stack([curve.tau_s**p for p in POWERS.values()]) * scale[:, None]
    norms = np.linalg.norm(design, axis=0)
    coef = nnls_few(design / norms, avar * scale)
    return {name: float(c / n) for name, c, n in zip(POWERS, coef, norms, strict=True)}


def nnls_few(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """argmin ‖a·x − b‖ over x ≥ 0, for a few columns: every subset of the columns solved by
    least squares, the best whose coefficients are all non-negative.

    Why not scipy's ``nnls``: importing ``scipy.optimize`` takes half a second, longer than the
    fit of a whole static record's curve. With three columns there are seven subsets; the
    problem is convex, so the best feasible subset solution is the optimum (its support's
    least squares), equal to an active-set solver's within rounding.
    """
    n = a.shape[1]
    best = np.zeros(n)
    best_rss = float(b @ b)
    for mask in range(1, 1 << n):
        cols = [j for j in range(n) if mask >> j & 1]
        x, *_ = np.linalg.lstsq(a[:, cols], b, rcond=None)
        if np.any(x < 0.0):
            continue
        r = b - a[:, cols] @ x
        rss = float(r @ r)
        if rss < best_rss:
            best = np.zeros(n)
            best[cols] = x
            best_rss = rss
    return best


@dataclass(frozen=True)
class NoiseTerms:
    """The three IEEE 952 read-outs of one curve, by name: readers (the report, the set's ARW, the
    plot) take the term they need as a field, not by a key spelled in each of them."""

    arw: NoiseTerm
    bias_instability: NoiseTerm
    rrw: NoiseTerm

    def items(self) -> tuple[tuple[str, NoiseTerm], ...]:
        """(report key, term) in the report's order."""
        return (("arw", self.arw), ("bias_instability", self.bias_instability), ("rrw", self.rrw))

    def __getitem__(self, key: str) -> NoiseTerm:
        """A term by its report key, for tables that loop over keys (tests/benchmarks/bench_allan.py)."""
        return dict(self.items())[key]

    def to_dict(self) -> dict[str, Any]:
        return {key: t.to_dict() for key, t in self.items()}


METHOD = ("overlapping Allan deviation (allantools); lines of slope -1/2, 0, +1/2 fitted together, "
          "IEEE Std 952 read-outs; intervals ±2/sqrt(2(K-1)) with K independent clusters where the "
          "term dominates")


@dataclass(frozen=True)
class NoiseAnalysis:
    """An Allan analysis as the report, the plot and ``canical noise`` read it: the curve and its terms.

    One record built once (:func:`canical.calibrate.noise_records.noise_analysis`) and read by field,
    so the keys of report.json are spelled once, in :meth:`to_dict`.
    """

    source: str
    curve: AllanCurve
    terms: NoiseTerms
    samples_per_point: int | None = None  # the records are means of this many samples

    @property
    def tau_range_s(self) -> tuple[float, float]:
        return float(self.curve.tau_s[0]), float(self.curve.tau_s[-1])

    def to_dict(self) -> dict[str, Any]:
        """The JSON form (report.json's ``allan``, ``canical noise --json``), keys in the file's order."""
        curve = self.curve
        low = int(np.argmin(curve.adev))
        out: dict[str, Any] = {
            "source": self.source,
            "method": METHOD,
            "records": curve.records,
            "duration_s": curve.duration_s,
            "sample_rate_hz": curve.sample_rate_hz,
            "tau_range_s": list(self.tau_range_s),
            "terms": self.terms.to_dict(),
            "curve_minimum": {
                "tau_s": float(curve.tau_s[low]),
                "adev_dps": float(curve.adev[low]),
                "bias_instability_deg_h": float(curve.adev[low]) / FLICKER_FLOOR * 3600.0,
            },
            "curve": {
                "tau_s": curve.tau_s.tolist(),
                "adev_dps": curve.adev.tolist(),
                "clusters": curve.clusters.tolist(),
            },
        }
        if self.samples_per_point is not None:
            out["samples_per_point"] = self.samples_per_point
        return out


@dataclass(frozen=True)
class NoiseSkipped:
    """No analysis, and why: the records had no evenly sampled stretch long enough."""

    source: str
    skipped: str

    def to_dict(self) -> dict[str, Any]:
        return {"source": self.source, "skipped": self.skipped}


def noise_terms(curve: AllanCurve) -> NoiseTerms:
    """ARW (deg/√h), bias instability (deg/h) and RRW (deg/h/√h) from a curve in deg/s.

    Read-outs of the fitted lines: ARW = σ of the −1/2 line at τ = 1 s (σ² = N²/τ), BI = level
    of the flat line / 0.664, RRW = σ of the +1/2 line at τ = 3 s (σ² = K²τ/3).
    """
    a = fit_terms(curve)
    total = np.zeros_like(curve.tau_s, dtype=float)
    for k, p in POWERS.items():
        total = total + a[k] * curve.tau_s**p
    hi = float(curve.tau_s[-1])
    lo = float(curve.tau_s[0])
    return NoiseTerms(
        arw=_term(curve, a, total, "arw", "angle random walk", "deg/sqrt(h)", np.sqrt, SQRT_HOUR,
                  f"white rate noise dominates nowhere between tau {lo:.3g} and {hi:.3g} s"),
        bias_instability=_term(
            curve, a, total, "bias_instability", "bias instability", "deg/h",
            lambda x: np.sqrt(x) / FLICKER_FLOOR, 3600.0,
            f"the curve has no flat floor between tau {lo:.3g} and {hi:.3g} s: a longer record is needed"),
        rrw=_term(curve, a, total, "rrw", "rate random walk", "deg/h/sqrt(h)",
                  lambda x: np.sqrt(RRW_TAU_S * x), 3600.0 * SQRT_HOUR,
                  f"the curve does not rise as tau^+1/2 up to {hi:.3g} s: a longer record is needed",
                  min_span=RRW_MIN_SPAN),
    )


def _term(curve: AllanCurve, a: dict[str, float], total: np.ndarray, key: str, name: str, unit: str,
          level: Callable[[float], float], to_unit: float, why: str, min_span: float = MIN_SPAN) -> NoiseTerm:
    """Resolved where the term dominates the fitted curve over a stretch of τ; interval from there.

    At the most precise such point (K clusters, share s of the variance) the term's σ is
    known to 1/√(2(K−1))/s; the interval is twice that either side. Not resolved: the line
    of its slope laid under the curve (each point raised by two of its errors) bounds it.
    """
    p = POWERS[key]
    share = a[key] * curve.tau_s**p / total
    e = curve.rel_error
    seen = share >= DOMINANT_SHARE
    if seen.any() and key == "rrw" and not _long_enough(curve.tau_s[seen], min_span):
        low, high = float(curve.tau_s[seen].min()), float(curve.tau_s[seen].max())
        why = (f"the curve rises between tau {low:.3g} and {high:.3g} s only, less than a decade reaching "
               f"{RRW_TAU_S:g} s: a drift, a rate ramp or a temperature change does that too; a longer "
               "record is needed")
    elif seen.any() and curve.tau_s[seen].max() >= min_span * curve.tau_s[seen].min():
        i = int(np.argmin(np.where(seen, e, np.inf)))
        value = float(level(a[key])) * to_unit
        rel = 2.0 * float(e[i] / share[i])
        if rel * CLAIM_SIGMAS / 2.0 < 1.0:
            return NoiseTerm(name, unit, True, value, value * max(1.0 - rel, 0.0), value * (1.0 + rel),
                             float(curve.tau_s[i]), int(curve.clusters[i]), "")
        why = (f"the curve's share of it between tau {float(curve.tau_s[seen].min()):.3g} and "
               f"{float(curve.tau_s[seen].max()):.3g} s is within {CLAIM_SIGMAS:g} of its errors of none: "
               "a longer record is needed")
    bound_var = (curve.adev * (1.0 + 2.0 * e)) ** 2 / curve.tau_s**p
    i = int(np.argmin(bound_var))
    value = float(level(bound_var[i])) * to_unit
    return NoiseTerm(name, unit, False, value, value, value, float(curve.tau_s[i]), int(curve.clusters[i]),
                     why)


def _long_enough(taus: np.ndarray, min_span: float) -> bool:
    """The τ where rate random walk dominates: a decade of it, reaching its read-out τ."""
    return bool(taus.max() >= min_span * taus.min() and taus.max() >= RRW_TAU_S)
