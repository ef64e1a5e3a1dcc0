"""Records for the Allan deviation: stretches of evenly sampled rate at zero input.

Why: the Allan deviation assumes one sample every 1/fs with none missing. A static record
that lost rows, or the zero-rate plateaus of a turntable session (each 10–60 s, separated
by the sweep), is cut into evenly sampled pieces, which :func:`canical.calibrate.allan.allan_deviation`
pools per cluster size; no sample is interpolated and no gap is averaged across.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from canical.calibrate.allan import NoiseAnalysis, NoiseSkipped, allan_deviation, noise_terms
from canical.models.robust_stats import median_step, time_steps

GAP_FACTOR = 1.5  # a step longer than this many sample intervals is a gap (rows lost)
MIN_RECORD = 6  # samples: three independent clusters of two


def first_backwards(time_s: np.ndarray) -> int | None:
    """Index of the first sample whose time is earlier than the one before, if any."""
    for first, steps in time_steps(time_s):
        bad = np.flatnonzero(steps < 0)
        if bad.size:
            return first + int(bad[0]) + 1
    return None


def sample_interval(time_s: np.ndarray) -> float:
    """The nominal interval: the median step (lost rows and jitter do not move it); 0 without one."""
    return median_step(time_s, 0.0)


def uniform_records(time_s: np.ndarray, rate: np.ndarray, dt: float) -> list[np.ndarray]:
    """The rate cut wherever a step exceeds ``GAP_FACTOR``·dt; pieces too short are dropped."""
    cuts = np.concatenate([np.zeros(0, dtype=np.intp),
                           *(first + np.flatnonzero(steps > GAP_FACTOR * dt) + 1
                             for first, steps in time_steps(time_s))])
    return [piece for piece in np.split(np.asarray(rate, dtype=float), cuts) if piece.size >= MIN_RECORD]


def zero_rate_records(
    time_s: np.ndarray, rate: np.ndarray, start: np.ndarray, stop: np.ndarray, dt: float
) -> list[np.ndarray]:
    """The used samples of each zero-rate plateau (``start``/``stop`` index ranges), cut at gaps."""
    out: list[np.ndarray] = []
    for a, b in zip(start, stop, strict=True):
        out += uniform_records(time_s[a:b], rate[a:b], dt)
    return out


def noise_analysis(records: list[np.ndarray], dt: float, source: str) -> NoiseAnalysis | NoiseSkipped:
    """The Allan analysis of the records, or why there is none."""
    if dt <= 0 or not records:
        return NoiseSkipped(source, f"no evenly sampled stretch of at least {MIN_RECORD} samples")
    curve = allan_deviation(records, 1.0 / dt)
    return NoiseAnalysis(source, curve, noise_terms(curve))


def name_a_rise(analysis: NoiseAnalysis, channel: str, values: np.ndarray, unit: str) -> NoiseAnalysis:
    """A rise of the curve not claimed as rate random walk, named for what moved in the records.

    When the curve rises over too short a stretch of τ to be rate random walk and ``channel``
    (the temperature) changes across the records, the note says by how much: that rise is the
    session's drift with it, not a noise term of the sensor.
    """
    rrw = analysis.terms.rrw
    if rrw.resolved or "rises" not in rrw.note or values.size < 2:
        return analysis
    span = float(np.max(values) - np.min(values))
    if span <= 0.0:
        return analysis
    note = f"{rrw.note}; the records' {channel} spans {span:.3g} {unit}: likely that drift"
    return replace(analysis, terms=replace(analysis.terms, rrw=replace(rrw, note=note)))


def describe(analysis: NoiseAnalysis | NoiseSkipped) -> list[str]:
    """Lines for a terminal or a report: the τ range and each term, resolved or not."""
    if isinstance(analysis, NoiseSkipped):
        return [f"noise analysis skipped: {analysis.skipped}"]
    curve = analysis.curve
    lo, hi = analysis.tau_range_s
    lines = [f"{analysis.source}: {curve.records} record(s), {curve.duration_s:.1f} s at "
             f"{curve.sample_rate_hz:.4g} Hz; tau {lo:.3g} to {hi:.3g} s"]
    for _, t in analysis.terms.items():
        if t.resolved:
            lines.append(f"{t.name:<18} {t.value:.4g} {t.unit} [{t.low:.3g}, {t.high:.3g}] "
                         f"(tau {t.tau_s:.3g} s, {t.clusters} clusters)")
        else:
            bound = f"at most {t.value:.3g} {t.unit}"
            lines.append(f"{t.name:<18} not resolved: {t.note} ({bound})")
    return lines


#: A static record's 1 s means stay within this of each other (the bias tracker's plausibility
#: bound: a mean beyond it is a turn, not a bias); more, and the record moved.
AT_REST_SPAN_DPS = 1.0


def motion_span_dps(time_s: np.ndarray, rate_dps: np.ndarray, window_s: float = 1.0) -> float:
    """How far the record's ``window_s`` means spread (0.5th to 99.5th percentile), deg/s.

    Why: the Allan terms describe a sensor at rest; on a record with motion they describe the
    motion (one such record gave a rate random walk of 2.95e5 deg/h/√h, without a word).
    """
    if len(time_s) < 2:
        return 0.0
    block = np.floor((np.asarray(time_s) - time_s[0]) / window_s).astype(np.int64)
    starts = np.flatnonzero(np.r_[True, np.diff(block) != 0])
    counts = np.diff(np.r_[starts, len(block)])
    means = np.add.reduceat(np.asarray(rate_dps, dtype=float), starts) / counts
    lo, hi = np.percentile(means, [0.5, 99.5])
    return float(hi - lo)

