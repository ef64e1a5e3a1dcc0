"""Sub-plateau blocks: the points the closed loop fits, with the conditions of each.

Plateau means hide what changes within a plateau (a warm-up, a temperature
drifting while the table turns). The closed loop therefore cuts each plateau into
blocks of a few seconds and keeps, per block, the mean ΔV, the table rate, the
mean of every auxiliary channel, the mean time since power-on and the direction
state the run time would compute from the raw signal. Blocks of one plateau
share its ``plateau`` index, so cross-validation can leave whole plateaus out.

Transforms of a channel that have state (its lag with a time constant still to
be estimated, its smoothed derivative, the direction of its last change) are
computed on the samples, in time order, as the run time would, and only then
averaged per block: :class:`ChannelSamples` does that on demand and caches it.
So is a channel gated by the rate (its level times a gate of the sample's own ΔV,
which is not the gate of the block's mean ΔV near the knee).

A smooth function S of a channel's lag is taken of the block's mean lag: S of the mean, not the
mean of S. Why: τ changes with every step of its search, and S per sample costs a pass over the
whole record for each τ and basis function (minutes per session); within a block of a few
seconds a lag of τ ≥ 5 s hardly moves, so the two differ by S's curvature times the lag's
variance within the block, far below the noise. For the same reason the lag whose τ the smooth
form searches runs on the channel's means over windows of ``COARSE_STEP_S`` (a few thousand
steps instead of a pass over every sample per τ), read at each block's mean time. A smooth
function of the channel's rate of change, whose τ is fixed, is averaged sample by sample (a
transient can cross S's bend within a block). The run time evaluates the lag and S per sample,
as the set says.

A session of more than :data:`FEATURE_SAMPLES` samples (hours at 1 kHz) keeps its channels, time
and ΔV for these transforms as means of a few consecutive samples (:func:`channel_samples`), never
across a block's edge, each weighted by its count in a block's mean. Why: every τ, knee and
candidate tried is a pass over the kept samples, and the confound checks try hundreds; on a
10-million-row session with two channels those passes were the whole run. A mean of ten samples
at 1 kHz spans 10 ms: a lag or a derivative's smoothing of τ ≥ 0.5 s hardly moves within it, and a
block's mean of a channel itself is exact. Sessions within the bound are not touched.

A session whose used plateaus would make more than :data:`MAX_BLOCKS` blocks of ``BLOCK_S``
(about 50 minutes of plateaus) is cut into longer blocks, as many as the bound
(:func:`block_length`). Why: every fit of the loop is a least-squares problem with a row per block,
tried tens of thousands of times, so a session of hours cost its length again in every one. What
the loop looks for changes over tens of seconds or more (a lag's τ ≥ 5 s, warm-ups, drifts, a
channel's swings), and a block's means of the samples' transforms are exact whatever its length;
a longer block has less noise, so the noise floor the loop's residual is judged against is
measured on the same blocks. Sessions within the bound keep blocks of ``BLOCK_S``.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np

from canical.calibrate.fit_points import FitPoints
from canical.calibrate.plateaus import Plateaus, plateau_means
from canical.sessions.session import Session
from canical.sets.term_kinds import (
    CHANNEL_DERIVATIVE_SPLINE,
    CHANNEL_DIRECTION,
    CHANNEL_GATED,
    CHANNEL_LAG,
    CHANNEL_LAG_SPLINE,
    CHANNEL_RATE_SPLINE,
    spline_horner,
    spline_segments,
    spline_values,
)
from canical.sets.term_params import Lag, LagSpline, Spline
from canical.sets.terms import Term, lag_filter, rate_gate
from canical.sets.trackers import direction_steps, slope_filter

BLOCK_S = 2.0
SLOPE_TAU_S = 0.5
#: Seconds of samples one step of the coarse lag averages (see the module's docstring).
COARSE_STEP_S = 0.25
#: Samples above which the channels' transforms run on means of consecutive samples (see above).
FEATURE_SAMPLES = 250_000
#: Blocks above which a session's blocks are made longer than ``BLOCK_S`` (:func:`block_length`).
MAX_BLOCKS = 1500


@dataclass(frozen=True)
class ChannelSamples:
    """Auxiliary channels sample by sample, and the sample range of every block.

    Block means of a channel's stateful transforms are computed once per
    (channel, transform, τ or threshold) and shared by every subset of blocks.
    """

    time_s: np.ndarray
    values: dict[str, np.ndarray]
    starts: np.ndarray
    stops: np.ndarray
    cache: dict[Any, np.ndarray] = field(default_factory=dict, compare=False)
    dv: np.ndarray | None = None  # raw − V0 per sample, for rate-gated transforms
    #: Samples behind each kept value (None: one each); a block's mean weighs its values by them.
    weights: np.ndarray | None = None

    def _make_room(self) -> None:
        """τ and knee searches visit many values: keep memory bounded by dropping theirs only.

        Clearing everything also dropped the direction states, which are computed sample by
        sample in Python and cost far more to redo than a lag or a gate.
        """
        if len(self.cache) > 512:
            searched = (CHANNEL_LAG, CHANNEL_GATED, CHANNEL_RATE_SPLINE, CHANNEL_LAG_SPLINE, "segments")
            for key in [k for k in self.cache if k[0] in searched]:
                del self.cache[key]

    def means(self, values: np.ndarray) -> np.ndarray:
        if self.weights is not None:
            values = values * self.weights
        csum = np.concatenate(([0.0], np.cumsum(values, dtype=float)))
        return (csum[self.stops] - csum[self.starts]) / self._counts()

    def _counts(self) -> np.ndarray:
        """Samples in each block (the weights' sums when the values are means)."""
        if ("counts",) not in self.cache:
            if self.weights is None:
                self.cache[("counts",)] = (self.stops - self.starts).astype(float)
            else:
                wsum = np.concatenate(([0.0], np.cumsum(self.weights)))
                self.cache[("counts",)] = wsum[self.stops] - wsum[self.starts]
        return self.cache[("counts",)]

    def lag_means(self, channel: str, tau_s: float) -> np.ndarray:
        """Block means of the channel's lag y with time constant τ (all blocks)."""
        key = (CHANNEL_LAG, channel, float(tau_s))
        if key not in self.cache:
            self._make_room()
            self.cache[key] = self.means(lag_filter(self.values[channel], self.time_s, tau_s))
        return self.cache[key]

    def derivative_spline_means(self, term: Term[LagSpline]) -> np.ndarray:
        """Block means of S((v − y)/τ) sample by sample (all blocks): the derivative's τ is not
        searched, so each sample's segment is found once per basis and kept; S of a block's mean
        rate would miss a transient S bends over within the block."""
        p = term.params
        tau = float(p.tau_s)
        key = ("derivative_spline", p.channel, tau, p.knots, p.pieces)
        if key not in self.cache:
            segments = ("derivative_segments", p.channel, tau, p.knots)
            if segments not in self.cache:
                values = self.values[p.channel]
                rate = (values - lag_filter(values, self.time_s, tau)) / tau
                i, u = spline_segments(p.knots, rate)
                self.cache[segments] = np.vstack([i.astype(float), u])
            seg = self.cache[segments]
            self.cache[key] = self.means(spline_horner(p.pieces, seg[0].astype(int), seg[1]))
        return self.cache[key]

    def coarse_lag_means(self, channel: str, tau_s: float) -> np.ndarray:
        """The channel's lag y with time constant τ at each block's mean time (all blocks), run on
        its means over windows of ``COARSE_STEP_S`` (whole windows; the lag of window means is the
        lag of the samples at each window's end where the channel holds within a window)."""
        key = (CHANNEL_LAG_SPLINE, channel, float(tau_s))
        if key not in self.cache:
            self._make_room()
            times, at = self._coarse_times()
            self.cache[key] = np.interp(at, times, lag_filter(self._coarse_values(channel), times, tau_s))
        return self.cache[key]

    def _coarse_step(self) -> int:
        """Samples per coarse window: ``COARSE_STEP_S`` at the median spacing, at least one."""
        steps = np.diff(self.time_s[: 1 + min(self.time_s.size - 1, 10_000)])
        spacing = float(np.median(steps)) if steps.size else 0.0
        return max(1, round(COARSE_STEP_S / spacing)) if spacing > 0 else 1

    def _coarse_times(self) -> tuple[np.ndarray, np.ndarray]:
        """The time of each coarse window's last sample, and each block's mean time."""
        if ("coarse_t",) not in self.cache:
            per = self._coarse_step()
            n = (self.time_s.size // per) * per or self.time_s.size
            self.cache[("coarse_t",)] = self.time_s[per - 1 : n : per] if n >= per else self.time_s[-1:]
            self.cache[("block_t",)] = self.means(self.time_s)
        return self.cache[("coarse_t",)], self.cache[("block_t",)]

    def _coarse_values(self, channel: str) -> np.ndarray:
        """The channel's mean over each coarse window."""
        key = ("coarse_v", channel)
        if key not in self.cache:
            per = self._coarse_step()
            values = self.values[channel]
            n = (values.size // per) * per
            self.cache[key] = values[:n].reshape(-1, per).mean(axis=1) if n else values[-1:]
        return self.cache[key]

    def spline_at(self, term: Term[LagSpline], x: np.ndarray) -> np.ndarray:
        """S of a transform spline's variable ``x`` at all blocks; each value's segment kept per
        (channel, kind, τ, knots), which a basis's terms share."""
        p = term.params
        key = ("segments", p.channel, term.feature, float(p.tau_s), p.knots)
        if key not in self.cache:
            self._make_room()
            i, u = spline_segments(p.knots, x)
            self.cache[key] = np.vstack([i.astype(float), u])
        seg = self.cache[key]
        return spline_horner(p.pieces, seg[0].astype(int), seg[1])

    def gated_means(self, channel: str, reference: float, knee_raw: float) -> np.ndarray:
        """Block means of (v − reference)·g(ΔV), the rate-gated level (all blocks).

        A knee search tries hundreds of knees. Where every sample of a block is beyond the knee,
        g = 1 − k/|ΔV| and the block's mean is mean(v − r) − k·mean((v − r)/|ΔV|), two means kept
        per channel; where none is, it is 0; only the blocks the knee falls within (their rate
        near it) are summed sample by sample.
        """
        if self.dv is None:
            raise ValueError("these samples were kept without their raw output")
        key = (CHANNEL_GATED, channel, float(reference), float(knee_raw))
        if key not in self.cache:
            self._make_room()
            level, per_dv = self._gate_parts(channel, float(reference))
            low, high = self._abs_dv_range()
            out = np.where(low > knee_raw, level - knee_raw * per_dv, 0.0)
            for b in np.flatnonzero((low <= knee_raw) & (high > knee_raw)):
                i, j = int(self.starts[b]), int(self.stops[b])
                gated = (self.values[channel][i:j] - reference) * rate_gate(self.dv[i:j], knee_raw)
                out[b] = self._slice_mean(i, j, gated)
            self.cache[key] = out
        return self.cache[key]

    def _gate_parts(self, channel: str, reference: float) -> tuple[np.ndarray, np.ndarray]:
        """Block means of v − r and of (v − r)/|ΔV| (0 where ΔV is 0: no block beyond a knee has it)."""
        key = ("gate_parts", channel, reference)
        if key not in self.cache:
            assert self.dv is not None
            offset = self.values[channel] - reference
            a = np.abs(self.dv)
            per_dv = np.divide(offset, a, out=np.zeros_like(offset), where=a > 0)
            self.cache[key] = np.vstack([self.means(offset), self.means(per_dv)])
        parts = self.cache[key]
        return parts[0], parts[1]

    def _abs_dv_range(self) -> tuple[np.ndarray, np.ndarray]:
        """The smallest and largest |ΔV| of each block's samples."""
        if ("abs_dv_range",) not in self.cache:
            assert self.dv is not None
            a = np.abs(self.dv)
            spans = [a[i:j] for i, j in zip(self.starts, self.stops, strict=True)]
            low = [x.min() if x.size else np.inf for x in spans]
            high = [x.max() if x.size else -np.inf for x in spans]
            self.cache[("abs_dv_range",)] = np.array([low, high], dtype=float)
        r = self.cache[("abs_dv_range",)]
        return r[0], r[1]

    def _slice_mean(self, i: int, j: int, values: np.ndarray) -> float:
        """The mean of ``values``, the samples i to j (weighted as :meth:`means` weighs them)."""
        if self.weights is None:
            return float(values.sum() / (j - i))
        w = self.weights[i:j]
        return float((values * w).sum() / w.sum())

    def rate_spline_means(self, term: Term[Spline]) -> np.ndarray:
        """Block means of (v − reference)·R(ΔV), a channel's coefficient smooth in rate (all blocks)."""
        if self.dv is None:
            raise ValueError("these samples were kept without their raw output")
        p = term.params
        key = (CHANNEL_RATE_SPLINE, p.channel, float(term.reference), p.knots, p.pieces)
        if key not in self.cache:
            self._make_room()
            offset = self.values[p.channel] - term.reference
            self.cache[key] = self.means(offset * spline_values(p.knots, p.pieces, self.dv))
        return self.cache[key]

    def abs_dv_means(self) -> np.ndarray:
        """Block means of |ΔV| (all blocks): where a knee in the rate can lie."""
        if ("abs_dv",) not in self.cache:
            self.cache[("abs_dv",)] = self.means(np.abs(self.dv)) if self.dv is not None else np.zeros(0)
        return self.cache[("abs_dv",)]

    def direction_means(self, channel: str, threshold: float) -> np.ndarray:
        """Block means of the sign of the channel's last change larger than ``threshold``."""
        key = (CHANNEL_DIRECTION, channel, float(threshold))
        if key not in self.cache:
            self.cache[key] = self.means(direction_steps(self.values[channel], threshold))
        return self.cache[key]


@dataclass(frozen=True)
class Blocks:
    """Block means; ``points`` are what a rate model is fitted to."""

    points: FitPoints
    plateau: np.ndarray  # plateau index of each block
    time_s: np.ndarray
    aux: dict[str, np.ndarray]
    direction: np.ndarray  # mean run-time direction state in the block
    direction_threshold_raw: float
    slope: np.ndarray  # mean run-time rate of change of raw (raw units/s) in the block
    samples: ChannelSamples | None = None  # for stateful channel transforms
    rows: np.ndarray | None = None  # these blocks' positions among the samples' blocks
    block_s: float = BLOCK_S  # the length each plateau is cut into (its last block longer)
    #: :meth:`take`'s subsets by their index: a cross-validation fold's blocks are the same object
    #: every time a structure is scored, so what is kept on them (``columns``) serves them all.
    #: Not init fields: blocks made by ``dataclasses.replace`` (other channels) start empty.
    subsets: dict[tuple[str, bytes], Blocks] = field(default_factory=dict, init=False, compare=False,
                                                     repr=False)
    #: The loop's term columns on these blocks (``closed_loop.candidates.shift_column``).
    columns: dict[tuple[Any, ...], np.ndarray] = field(default_factory=dict, init=False, compare=False,
                                                       repr=False)

    def __len__(self) -> int:
        return len(self.points)

    @property
    def label(self) -> str:
        """What the loop's figures are measured on, for reports: ``2 s blocks``."""
        return block_label(self.block_s)

    def take(self, index: np.ndarray) -> Blocks:
        """The blocks at ``index`` (a mask or positions), the same object for the same index: its
        own :attr:`columns` then serve every structure scored on that fold."""
        index = np.asarray(index)
        key = (index.dtype.str, index.tobytes())
        if key not in self.subsets:
            self.subsets[key] = self._taken(index)
        return self.subsets[key]

    def _taken(self, index: np.ndarray) -> Blocks:
        rows = np.arange(len(self)) if self.rows is None else self.rows
        return Blocks(
            self.points.take(index),
            self.plateau[index],
            self.time_s[index],
            {k: v[index] for k, v in self.aux.items()},
            self.direction[index],
            self.direction_threshold_raw,
            self.slope[index],
            self.samples,
            rows[index],
            self.block_s,
        )

    def with_shifted(self, channel: str, name: str, fraction: float) -> Blocks:
        """These blocks with a copy of ``channel`` under ``name``, shifted in time by ``fraction``
        of the session along the channel followed by its own reverse (read around as a circle):
        the channel's values, wander and range, no longer in step with the sensor. The samples'
        cache is shared (its keys name the channel), the columns are not.

        Why: two slowly wandering records (a channel that random-walks, a sensor's bias that steps)
        fit each other by chance, often well; what a form takes of the channel shifted against the
        sensor says how well (``closed_loop.search.shifted_stretch_gain``). Why the reverse: a plain
        circle joins the record's end to its start, a jump no copy would have, which a form of the
        channel then fits as a bias step or not at all.
        """
        if self.samples is None:
            raise ValueError("these blocks were built without their samples")
        values = self.samples.values[channel]
        start = round(fraction * values.size)
        shifted = np.concatenate([values, values[::-1]]).take(np.arange(start, start + values.size),
                                                               mode="wrap")
        samples = replace(self.samples, values={**self.samples.values, name: shifted},
                          cache=self.samples.cache)
        rows = slice(None) if self.rows is None else self.rows
        return replace(self, aux={**self.aux, name: samples.means(shifted)[rows]}, samples=samples)

    def channel_feature(self, term: Term) -> np.ndarray:
        """Block means of a channel transform computed on samples (lag, derivative, direction, gated,
        a smooth function of the derivative); a smooth function of the lag, of its block mean."""
        if self.samples is None:
            raise ValueError("these blocks were built without their samples")
        rows = slice(None) if self.rows is None else self.rows
        if CHANNEL_GATED.owns(term):
            p = term.params
            return self.samples.gated_means(p.channel, term.reference, p.threshold_raw)[rows]
        if CHANNEL_RATE_SPLINE.owns(term):
            return self.samples.rate_spline_means(term)[rows]
        if CHANNEL_DIRECTION.owns(term):
            return self.samples.direction_means(term.params.channel, term.params.threshold_raw)[rows]
        if CHANNEL_DERIVATIVE_SPLINE.owns(term):
            return self.samples.derivative_spline_means(term)[rows]
        if CHANNEL_LAG_SPLINE.owns(term):  # of the lag, τ searched: the coarse lag
            lag = self.samples.coarse_lag_means(term.params.channel, term.params.tau_s)
            return self.samples.spline_at(term, lag)[rows]
        if not isinstance(term.params, Lag):
            raise TypeError(f"{term.describe()} is not a channel transform computed on samples")
        ch, tau = term.params.channel, term.params.tau_s
        y = self.samples.lag_means(ch, tau)[rows]
        if term.spec is CHANNEL_LAG:
            return y - term.reference
        return (self.aux[ch] - y) / tau


def channel_samples(time_s: np.ndarray, aux: dict[str, np.ndarray], starts: np.ndarray,
                    stops: np.ndarray, dv: np.ndarray) -> ChannelSamples:
    """The samples the channels' transforms run on: as they are up to :data:`FEATURE_SAMPLES`;
    above, means of ``k`` consecutive samples (fewer where a block's edge falls), ``k`` the
    smallest that brings them to the bound, each block's edges kept as edges."""
    n = time_s.size
    k = -(-n // FEATURE_SAMPLES)
    if k <= 1:
        return ChannelSamples(time_s, dict(aux), starts, stops, dv=dv)
    edges = np.unique(np.concatenate([np.arange(0, n, k), starts, stops, [n]]))
    counts = np.diff(edges).astype(float)

    def binned(values: np.ndarray) -> np.ndarray:
        return np.add.reduceat(np.asarray(values, dtype=float), edges[:-1]) / counts

    return ChannelSamples(binned(time_s), {name: binned(v) for name, v in aux.items()},
                          np.searchsorted(edges, starts), np.searchsorted(edges, stops), dv=binned(dv),
                          weights=counts)


def _block_bounds(plateaus: Plateaus, time_s: np.ndarray, block_s: float) -> tuple[np.ndarray, ...]:
    starts: list[int] = []
    stops: list[int] = []
    owner = []
    for p, (a, b) in enumerate(zip(plateaus.start, plateaus.stop, strict=True)):
        duration = time_s[b - 1] - time_s[a]
        n = max(1, int(duration // block_s))
        edges = np.linspace(a, b, n + 1).round().astype(int)
        starts.extend(edges[:-1])
        stops.extend(edges[1:])
        owner.extend([p] * n)
    return np.array(starts), np.array(stops), np.array(owner)


def _block_rates(ref: np.ndarray, plateaus: Plateaus, means: Callable[[np.ndarray], np.ndarray],
                 owner: np.ndarray) -> np.ndarray:
    """Each block's table rate: the mean reference over it, and on a sweep's windows shifted as its
    window's rate was (by the sensor's delay behind the reference times the sweep rate): on a
    sweep that delay is a rate error of opposite sign in the two directions, which the loop would
    otherwise take for an effect of the rate's direction or change."""
    rate = means(ref)
    if plateaus.sweep_window_s > 0:
        rate = rate + (plateaus.rate_dps - plateau_means(ref, plateaus))[owner]
    return rate


def block_label(block_s: float) -> str:
    """Blocks of ``block_s`` seconds as every report names them: ``2 s blocks``, ``6.7 s blocks``."""
    return f"{block_s:.2g} s blocks"


def block_length(plateaus: Plateaus, time_s: np.ndarray, keep: np.ndarray | None = None) -> float:
    """Seconds per block: ``BLOCK_S``, or longer where the used plateaus would make more than
    :data:`MAX_BLOCKS` of them (see the module's docstring)."""
    used = time_s[plateaus.stop - 1] - time_s[plateaus.start]
    if keep is not None:
        used = used[keep]
    return max(BLOCK_S, float(np.sum(used)) / MAX_BLOCKS)


def make_blocks(
    session: Session,
    plateaus: Plateaus,
    v0: float,
    *,
    keep: np.ndarray | None = None,
    direction_threshold_raw: float,
) -> Blocks:
    """Cut the used plateaus (``keep`` masks plateaus, e.g. unsaturated ones) into blocks of
    :func:`block_length`."""
    block_s = block_length(plateaus, session.time_s, keep)
    starts, stops, owner = _block_bounds(plateaus, session.time_s, block_s)
    if keep is not None:
        sel = keep[owner]
        starts, stops, owner = starts[sel], stops[sel], owner[sel]
    n = (stops - starts).astype(float)

    def means(values: np.ndarray) -> np.ndarray:
        csum = np.concatenate(([0.0], np.cumsum(values, dtype=float)))
        return (csum[stops] - csum[starts]) / n

    raw = session.raw
    mean_raw = means(raw)
    sd = np.sqrt(np.maximum(means(raw * raw) - mean_raw**2, 0.0) * n / np.maximum(n - 1, 1))
    points = FitPoints(_block_rates(session.reference(), plateaus, means, owner), mean_raw - v0, n,
                       sd / np.sqrt(n))
    direction = direction_steps(raw, direction_threshold_raw)
    return Blocks(
        points=points,
        plateau=owner,
        time_s=means(session.time_s),
        aux={name: means(values) for name, values in session.aux.items()},
        direction=means(direction),
        direction_threshold_raw=direction_threshold_raw,
        slope=means(slope_filter(raw, session.time_s, SLOPE_TAU_S)),
        block_s=block_s,
        samples=channel_samples(session.time_s, session.aux, starts, stops, raw - v0),
    )
