"""Candidate explanations of a residual, built from the session itself.

Every auxiliary column is a source of candidates by its name (its meaning is
never assumed), in the forms a calibration engineer would try when a sensor
feels a channel other than directly:

* ``channel:<ch>`` — its level (and its square);
* ``d/dt <ch>`` — its rate of change, smoothed over a window chosen from the
  channel's own noise (a thermal transient: the die heats before the sensor reads);
* ``lag(<ch>)`` — the channel seen through a first-order lag whose τ is
  estimated (the sensor feels the channel late);
* ``sign d/dt <ch>`` — the direction of its last significant change, with a
  threshold above its noise (hysteresis: heating vs cooling);
* ``<ch> × (|rate| > knee)`` — its level acting only beyond a knee in the
  output, |ΔV| > k, with k estimated like a time constant (an effect that
  switches on with rate: a drive loop near its limit).

* ``smooth(<ch> × rate)`` — its level times a smooth function of the output ΔV, learned the
  same way (cubic B-splines of ΔV, knots at quantiles of the plateaus' ΔV): a coefficient of the
  channel that changes with rate, e.g. a scale-factor temperature coefficient that depends on
  rate (the nonlinearity's shape changing with temperature). It nests the channel's level.
* ``smooth(<ch>)`` — its effect as a smooth function learned from the data: a cubic
  B-spline of its level with knots at quantiles of its plateau levels (a bias that follows
  the square of a wide-ranging channel, or saturates with it), built only where the channel
  takes enough distinct levels to fit one. It competes as one more candidate with the same
  held-out plateaus, F-test (charged for every basis column) and paired tests; it nests the
  channel's level and square, so where the two tie the level is taken (see
  :mod:`canical.closed_loop.search`). Clean sensors and effects on the list add no spline.
* ``smooth(lag(<ch>))`` — the same smooth form of the channel's lag, τ estimated as the lag's
  (a bias saturating with the temperature the die feels late), knots evenly spaced over the
  span of the channel's plateau levels (the range the lag moves in), built only where those
  levels stand out of the channel's noise; it nests the lag, the smooth form of the level and
  the level. ``smooth(d/dt <ch>)`` — of its rate of change smoothed over the
  derivative's window (a transient whose size is not proportional to the rate), knots at
  quantiles of the plateau means of that rate, built only where the window resolves the rate
  above the channel's noise; it nests the rate of change.

Time since power-on brings a warm-up 1 − exp(−t/τ) with τ estimated and a
linear drift; the table brings the direction of approach (the raw signal's last
significant change) and its rate of change. Each candidate brings its terms in
bias form (ΔV gains c·x) and scale-factor form (ΔV gains c·x·ΔV). Columns that
do not earn their keep are pruned after acceptance.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, replace

import numpy as np
from scipy.interpolate import BSpline

from canical.closed_loop.blocks import SLOPE_TAU_S, Blocks
from canical.models.robust_stats import mad_sigma
from canical.sets.term_kinds import (
    CHANNEL,
    CHANNEL_DERIVATIVE,
    CHANNEL_DERIVATIVE_SPLINE,
    CHANNEL_DIRECTION,
    CHANNEL_GATED,
    CHANNEL_LAG,
    CHANNEL_LAG_SPLINE,
    CHANNEL_OFFSET,
    CHANNEL_RATE_SPLINE,
    CHANNEL_SPLINE,
    CHANNEL_SQUARE,
    DIRECTION,
    DIRECTION_SIGN,
    DIRECTION_SLOPE,
    TIME,
    TIME_LINEAR,
    TIME_WARMUP,
    TermKind,
    spline_values,
)
from canical.sets.term_params import Spline, Tau, Threshold
from canical.sets.terms import Term

TAU_GRID_POINTS = 24
LAG_GRID_POINTS = 12
# Hysteresis threshold: this many per-sample noise sigmas (a noise excursion
# over a whole session stays below it), and at least this share of the range.
DIRECTION_NOISE_SIGMAS = 10.0
DIRECTION_MIN_SHARE = 0.02
# Derivative window: the shortest whose block-mean noise is this share of the
# derivative's spread (or the longest tried).
DERIVATIVE_NOISE_SHARE = 0.1
DERIVATIVE_WINDOWS_S = (2.0, 4.0, 8.0, 15.0, 30.0, 60.0)
# Knees of a rate-gated effect worth trying: shares of the largest |ΔV| of the session
# (below the lowest the gate is 1 nearly everywhere: the plain level; above the highest
# too few plateaus lie beyond it to fit anything).
KNEE_GRID_POINTS = 10
KNEE_SHARES = (0.03, 0.8)
# A smooth candidate: at most this many interior knots, at quantiles of the channel's plateau
# levels; one interior knot more per SMOOTH_LEVELS_PER_KNOT distinct levels beyond the
# SMOOTH_MIN_LEVELS a cubic needs (levels closer than SMOOTH_LEVEL_SHARE of the range are one).
SMOOTH_MAX_INTERIOR = 5
SMOOTH_MIN_LEVELS = 8
SMOOTH_LEVELS_PER_KNOT = 3
SMOOTH_LEVEL_SHARE = 0.005
# A smooth form of a channel's lag only where its plateau levels spread this many times the
# noise of a plateau's mean.
LEVELS_RESOLVED = 10.0
# A channel's coefficient smooth in rate: fewer interior knots, since each basis function's
# coefficient rests on the channel's spread among the plateaus in its span of rates only.
RATE_SMOOTH_MAX_INTERIOR = 2
# The names of the candidates that are not a channel's.
WARMUP_NAME = f"{TIME}:warm-up"
DRIFT_NAME = f"{TIME}:linear-drift"
DIRECTION_NAME = DIRECTION
SLOPE_NAME = "rate-of-change"
# The nonlinear parameter a fit estimates for each kind that has one (see :func:`tau_groups`):
# a time constant, shared by all warm-up terms and by a channel's lag terms, or a gated channel's knee.
WARMUP_GROUP: tuple[str, str | None] = (TIME_WARMUP.feature, None)
GROUPED = (TIME_WARMUP, CHANNEL_LAG, CHANNEL_GATED, CHANNEL_LAG_SPLINE)


@dataclass(frozen=True)
class Candidate:
    """A named group of term templates (coefficients still to be fitted)."""

    name: str
    kind: str  # a term kind: CHANNEL | TIME | DIRECTION
    channel: str | None
    terms: tuple[Term, ...]

    def describe(self) -> str:
        return self.name

    def with_terms(self, terms: tuple[Term, ...]) -> Candidate:
        return replace(self, terms=terms)


def _level(term: Term, blocks: Blocks) -> np.ndarray:
    assert term.channel is not None  # a channel term names its channel (validation checks)
    x: np.ndarray = blocks.aux[term.channel] - term.reference
    return x


def _square(term: Term, blocks: Blocks) -> np.ndarray:
    x = _level(term, blocks)
    return x * x


def _warmup(term: Term, blocks: Blocks) -> np.ndarray:
    assert isinstance(term.params, Tau)  # BLOCK_FEATURES dispatches on the kind
    x: np.ndarray = 1.0 - np.exp(-blocks.time_s / term.params.tau_s)
    return x


def _spline(term: Term, blocks: Blocks) -> np.ndarray:
    assert isinstance(term.params, Spline)  # BLOCK_FEATURES dispatches on the kind
    return spline_values(term.params.knots, term.params.pieces, blocks.aux[term.params.channel])


#: Each term kind's feature at block level; a test checks that every kind of the registry is here.
BLOCK_FEATURES: dict[TermKind, Callable[[Term, Blocks], np.ndarray]] = {
    CHANNEL_OFFSET: _level,
    CHANNEL_SQUARE: _square,
    CHANNEL_LAG: lambda term, blocks: blocks.channel_feature(term),
    CHANNEL_DERIVATIVE: lambda term, blocks: blocks.channel_feature(term),
    CHANNEL_DIRECTION: lambda term, blocks: blocks.channel_feature(term),
    CHANNEL_GATED: lambda term, blocks: blocks.channel_feature(term),
    CHANNEL_RATE_SPLINE: lambda term, blocks: blocks.channel_feature(term),
    CHANNEL_LAG_SPLINE: lambda term, blocks: blocks.channel_feature(term),
    CHANNEL_DERIVATIVE_SPLINE: lambda term, blocks: blocks.channel_feature(term),
    CHANNEL_SPLINE: _spline,
    TIME_WARMUP: _warmup,
    TIME_LINEAR: lambda term, blocks: blocks.time_s,
    DIRECTION_SIGN: lambda term, blocks: blocks.direction,
    DIRECTION_SLOPE: lambda term, blocks: blocks.slope,
}


def feature(term: Term, blocks: Blocks) -> np.ndarray:
    """The term's feature x at each block (block means of the run-time inputs)."""
    return BLOCK_FEATURES[term.spec](term, blocks)


def shift_columns(terms: tuple[Term, ...], blocks: Blocks) -> np.ndarray:
    """Per term, what one unit of its coefficient adds to ΔV at each block: x, or x·ΔV."""
    if not terms:
        return np.zeros((len(blocks), 0))
    return np.column_stack([shift_column(t, blocks) for t in terms])


#: Columns :func:`shift_column` keeps per blocks before it starts again (a τ search's are many).
KEPT_COLUMNS = 512


def shift_column(term: Term, blocks: Blocks) -> np.ndarray:
    """One term's column of :func:`shift_columns`, kept on the blocks (read-only) by what the term
    computes (its coefficient aside).

    Why: a time constant's search fits the structure again at every τ it tries, and each fit
    computed every term's column again, though only the searched group's change; a fold's blocks
    are the same for every structure scored, so a term's column there is asked for again too.
    """
    kept = blocks.columns
    key = (term.spec, term.form, term.params, term.reference)
    column = kept.get(key)
    if column is None:
        column = feature(term, blocks) * (blocks.points.dv if term.form == "scale" else 1.0)
        column.setflags(write=False)
        if len(kept) >= KEPT_COLUMNS:
            kept.clear()
        kept[key] = column
    return column


def _pair(spec: TermKind, **kw) -> tuple[Term, ...]:
    return tuple(Term.of(spec, form, 0.0, **kw) for form in ("bias", "scale"))


TIED_R2 = 0.98


def tied_to_rate(x: np.ndarray, blocks: Blocks) -> float:
    """R² of a feature explained by a cubic of the table rate.

    When the session visits the rates in time order, time since power-on *is* the
    table rate, and a time term would predict the reference instead of the
    sensor's error: a leak that vanishes in the field. Such a candidate cannot be
    tested on this session.
    """
    rate = blocks.points.rate
    w = blocks.points.weight
    design = np.vander(rate / max(np.max(np.abs(rate)), 1e-9), 4, increasing=True)
    sw = np.sqrt(w)
    coef, *_ = np.linalg.lstsq(design * sw[:, None], x * sw, rcond=None)
    resid = x - design @ coef
    total = np.sum(w * (x - np.average(x, weights=w)) ** 2)
    return float(1.0 - np.sum(w * resid**2) / total) if total > 0 else 1.0


def untestable(candidates: list[Candidate], blocks: Blocks) -> dict[str, float]:
    """Candidates whose feature is a function of the table rate in this session, with that R²."""
    out = {}
    for cand in candidates:
        r2 = tied_to_rate(feature(cand.terms[0], blocks), blocks)
        if r2 >= TIED_R2:
            out[cand.name] = r2
    return out


def build_candidates(blocks: Blocks, session_duration_s: float) -> list[Candidate]:
    """All candidates this session can support (a channel that never varies cannot explain anything)."""
    out: list[Candidate] = []
    for name, values in sorted(blocks.aux.items()):
        if np.ptp(values) <= 1e-12 * max(1.0, float(np.max(np.abs(values)))):
            continue
        ref = float(np.mean(values))
        terms = (
            *_pair(CHANNEL_OFFSET, channel=name, reference=ref),
            Term.of(CHANNEL_SQUARE, "bias", 0.0, channel=name, reference=ref),
        )
        out.append(Candidate(CHANNEL_OFFSET.label(name), CHANNEL, name, terms))
        out.extend(_transform_candidates(blocks, name, ref, session_duration_s))
        smooth = smooth_terms(name, plateau_levels(blocks, name))
        if smooth:
            out.append(Candidate(CHANNEL_SPLINE.label(name), CHANNEL, name, smooth))
        by_rate = rate_smooth_terms(name, ref, plateau_means(blocks, blocks.points.dv))
        if by_rate and blocks.samples is not None and blocks.samples.dv is not None:
            out.append(Candidate(CHANNEL_RATE_SPLINE.label(name), CHANNEL, name, by_rate))
    if np.ptp(blocks.time_s) > 0:
        tau = float(session_duration_s) / 3.0
        out.append(Candidate(WARMUP_NAME, TIME, None, _pair(TIME_WARMUP, tau_s=tau)))
        out.append(Candidate(DRIFT_NAME, TIME, None, _pair(TIME_LINEAR)))
    if np.ptp(blocks.direction) > 0:
        out.append(
            Candidate(
                DIRECTION_NAME,
                DIRECTION,
                None,
                _pair(DIRECTION_SIGN, threshold_raw=blocks.direction_threshold_raw),
            )
        )
    # On settled plateaus the rate of change is near zero; it is a candidate all the same,
    # so that a sensor still moving in its plateaus would show it.
    if np.ptp(blocks.slope) > 0:
        out.append(
            Candidate(SLOPE_NAME, DIRECTION, None, _pair(DIRECTION_SLOPE, tau_s=SLOPE_TAU_S))
        )
    return out


def plateau_levels(blocks: Blocks, channel: str) -> np.ndarray:
    """The channel's mean over each plateau: the levels a smooth effect of it is learned from."""
    return plateau_means(blocks, blocks.aux[channel])


def plateau_means(blocks: Blocks, values: np.ndarray) -> np.ndarray:
    """The mean of a block quantity over each plateau."""
    _, idx = np.unique(blocks.plateau, return_inverse=True)
    return np.bincount(idx, values) / np.bincount(idx)


def smooth_terms(channel: str, levels: np.ndarray, form: str = "bias") -> tuple[Term, ...]:
    """The cubic B-spline basis of ``channel`` over the span of ``levels``, one spline term per
    basis function (its coefficient still to fit), the first left out: the rate model's own
    constant plus the others span every cubic spline on these knots. Empty when the levels are
    too few to fit one (a channel stepped between a handful of values says what the level and
    square say).

    Why B-splines: each basis function is local and bounded (0 to 1), so the least squares stay
    well conditioned and a basis column the data do not support is pruned without disturbing the
    others; each is written into the set in piecewise-polynomial form (a segment lookup and a
    cubic per sample).
    """
    basis = bspline_basis(levels)
    if basis is None:
        return ()
    breaks, pieces = basis
    return tuple(Term.of(CHANNEL_SPLINE, form, 0.0, channel=channel, knots=breaks, pieces=p)
                 for p in pieces[1:])


def transform_smooth_terms(spec: TermKind, channel: str, levels: np.ndarray, tau_s: float,
                           even: bool) -> tuple[Term, ...]:
    """The cubic B-spline basis of a transform of ``channel`` (``spec`` a ``lag_spline`` or
    ``derivative_spline`` with its ``tau_s``) over the span of ``levels``, the range the transform
    moves in, as :func:`smooth_terms` builds it, with interior knots evenly spaced (``even``: a lag
    sweeps the whole range between the channel's levels, which cluster where the channel held) or
    at the levels' quantiles.

    The middle basis function is left out, not the first: at a long τ the lag never reaches the
    ends of the channel's range, and on data that miss the left-out function's support the
    others sum to one there, a column the rate model's constant already is (the fit's
    coefficients then run off; seen: held-out rms 10¹⁷ at the true τ). Every lag passes through
    the middle of the range, a rate of change through zero.
    """
    basis = bspline_basis(levels, even=even)
    if basis is None:
        return ()
    breaks, pieces = basis
    middle = len(pieces) // 2
    return tuple(Term.of(spec, "bias", 0.0, channel=channel, knots=breaks, pieces=p, tau_s=tau_s)
                 for j, p in enumerate(pieces) if j != middle)


def rate_smooth_terms(channel: str, reference: float, dv_levels: np.ndarray) -> tuple[Term, ...]:
    """The channel's level times each cubic B-spline basis function of ΔV over the span of the
    plateaus' ``dv_levels``: a coefficient of the channel that changes smoothly with rate (a
    scale-factor temperature coefficient that depends on rate). All basis functions: they sum to
    one, so together they hold the channel's plain level, and in ΔV the scale form too. Bias form
    only (R(ΔV) holds ΔV itself where the data want it). Empty when the rates are too few."""
    basis = bspline_basis(dv_levels, RATE_SMOOTH_MAX_INTERIOR)
    if basis is None:
        return ()
    breaks, pieces = basis
    return tuple(Term.of(CHANNEL_RATE_SPLINE, "bias", 0.0, channel=channel, reference=reference,
                         knots=breaks, pieces=p) for p in pieces)


def bspline_basis(levels: np.ndarray, max_interior: int = SMOOTH_MAX_INTERIOR, even: bool = False
                  ) -> tuple[tuple[float, ...], list[tuple[tuple[float, ...], ...]]] | None:
    """The breaks and each basis function's pieces (piecewise-polynomial form) of a cubic B-spline
    over the span of ``levels`` with interior knots at their quantiles (``even``: evenly spaced),
    one more per SMOOTH_LEVELS_PER_KNOT distinct levels up to ``max_interior``; None when the
    levels are too few to fit one."""
    levels = np.sort(np.asarray(levels, dtype=float))
    span = float(levels[-1] - levels[0]) if levels.size else 0.0
    if not span > 0:
        return None
    distinct = 1 + int(np.sum(np.diff(levels) > SMOOTH_LEVEL_SHARE * span))
    n_interior = min(max_interior, (distinct - SMOOTH_MIN_LEVELS) // SMOOTH_LEVELS_PER_KNOT + 1)
    if n_interior < 1:
        return None
    lo, hi = float(levels[0]), float(levels[-1])
    shares = np.linspace(0.0, 1.0, n_interior + 2)[1:-1]
    interior = lo + shares * (hi - lo) if even else np.quantile(levels, shares)
    breaks = np.unique(np.concatenate([[lo], interior, [hi]]))
    knots = np.concatenate([[lo] * 3, breaks, [hi] * 3])
    n_basis = knots.size - 4
    out = []
    for j in range(n_basis):
        basis = BSpline(knots, np.eye(n_basis)[j], 3)
        derivs = [basis.derivative(d) if d else basis for d in range(4)]
        out.append(tuple(tuple(float(derivs[d](b)) / (1.0, 1.0, 2.0, 6.0)[d] for d in range(4))
                         for b in breaks[:-1]))
    return tuple(float(b) for b in breaks), out


def sample_noise(values: np.ndarray) -> float:
    """Per-sample white noise of a channel, robustly from successive differences."""
    d = np.diff(np.asarray(values, dtype=float))
    if d.size == 0:
        return 0.0
    return mad_sigma(d) / float(np.sqrt(2.0))


def _derivative_window(blocks: Blocks, channel: str) -> tuple[float, bool]:
    """The derivative's window, and whether at it the noise is a small share (resolved).

    Per block, the derivative (v − y)/τ carries the channel's noise σ divided by
    τ·sqrt(samples per block); the window is the shortest for which that is a
    small share of the derivative's spread over the session (else the longest tried).
    """
    samples = blocks.samples
    assert samples is not None
    sigma = sample_noise(samples.values[channel])
    per_block = float(np.median(samples.stops - samples.starts))
    for tau in DERIVATIVE_WINDOWS_S:
        d = feature(Term.of(CHANNEL_DERIVATIVE, "bias", 0.0, channel=channel, tau_s=tau), blocks)
        if sigma / (tau * np.sqrt(per_block)) <= DERIVATIVE_NOISE_SHARE * float(np.std(d)):
            return tau, True
    return DERIVATIVE_WINDOWS_S[-1], False


def direction_threshold(values: np.ndarray) -> float:
    """Hysteresis threshold of a channel: well above its noise, and a visible share of its range."""
    return max(DIRECTION_NOISE_SIGMAS * sample_noise(values), DIRECTION_MIN_SHARE * float(np.ptp(values)),
               1e-12)


def _transform_candidates(blocks: Blocks, name: str, ref: float, duration_s: float) -> list[Candidate]:
    """The channel's stateful transforms: derivative, lag, direction of change."""
    if blocks.samples is None or name not in blocks.samples.values:
        return []
    values = blocks.samples.values[name]
    knees = knee_grid(blocks)
    gated = [Candidate(CHANNEL_GATED.label(name), CHANNEL, name,
                       _gated_terms(name, ref, float(np.ptp(values)), float(np.sqrt(knees[0] * knees[-1]))))
             ] if knees.size else []
    tau_d, resolved = _derivative_window(blocks, name)
    tau_lag = float(np.sqrt(lag_grid(duration_s)[0] * lag_grid(duration_s)[-1]))
    thr = direction_threshold(values)
    return [
        Candidate(CHANNEL_DERIVATIVE.label(name), CHANNEL, name,
                  _pair(CHANNEL_DERIVATIVE, channel=name, tau_s=tau_d)),
        Candidate(CHANNEL_LAG.label(name), CHANNEL, name,
                  _pair(CHANNEL_LAG, channel=name, reference=ref, tau_s=tau_lag)),
        Candidate(CHANNEL_DIRECTION.label(name), CHANNEL, name,
                  _pair(CHANNEL_DIRECTION, channel=name, threshold_raw=thr)),
        *gated,
        *_transform_smooth(blocks, name, tau_lag, tau_d if resolved else None),
    ]


def _transform_smooth(blocks: Blocks, name: str, tau_lag: float, tau_d: float | None) -> list[Candidate]:
    """The smooth forms of the channel's lag (τ estimated as the lag's; knots over the channel's
    plateau levels, the range its lag moves in, evenly spaced) and of its rate of change (the derivative's
    window ``tau_d``; knots over the plateau means of that rate; None: the window does not
    resolve the rate above the channel's noise, whose smooth form would be one of noise),
    where there are levels enough for a spline."""
    out = []
    levels = plateau_levels(blocks, name)
    lag = transform_smooth_terms(CHANNEL_LAG_SPLINE, name, levels, tau_lag, even=True)
    if lag and _levels_resolved(blocks, name, levels):
        out.append(Candidate(CHANNEL_LAG_SPLINE.label(name), CHANNEL, name, lag))
    if tau_d is not None:
        rate = feature(Term.of(CHANNEL_DERIVATIVE, "bias", 0.0, channel=name, tau_s=tau_d), blocks)
        derivative = transform_smooth_terms(CHANNEL_DERIVATIVE_SPLINE, name, plateau_means(blocks, rate),
                                            tau_d, even=False)
        if derivative:
            out.append(Candidate(CHANNEL_DERIVATIVE_SPLINE.label(name), CHANNEL, name, derivative))
    return out


def _levels_resolved(blocks: Blocks, name: str, levels: np.ndarray) -> bool:
    """Whether the channel's plateau levels differ by more than the noise of a plateau's mean
    (``LEVELS_RESOLVED`` times): a channel of noise about a constant has a constant lag, and a
    smooth form of it would fit that noise (and cost a τ search each time it is scored)."""
    samples = blocks.samples
    assert samples is not None
    per_plateau = float(np.sum(samples.stops - samples.starts)) / max(levels.size, 1)
    noise = sample_noise(samples.values[name]) / np.sqrt(max(per_plateau, 1.0))
    return float(np.std(levels)) > LEVELS_RESOLVED * noise


def _gated_terms(name: str, ref: float, spread: float, knee_raw: float) -> tuple[Term, ...]:
    """The gated level in bias and scale form, and a second scale term with another reference.

    The level at which the effect vanishes is unknown (the session's mean is not it), and
    unlike a plain level a wrong reference here leaves a hinge of the rate, which the rate
    model cannot absorb. Two references span c·(v − r) for every r: the bias multiplied by
    the hinge, in terms the set already carries.
    """
    return (*_pair(CHANNEL_GATED, channel=name, reference=ref, threshold_raw=knee_raw),
            Term.of(CHANNEL_GATED, "scale", 0.0, channel=name, reference=ref - (spread or 1.0),
                    threshold_raw=knee_raw))


def knee_grid(blocks: Blocks) -> np.ndarray:
    """Knees (raw units) of a rate-gated effect worth trying, from the whole session's blocks.

    The same grid for every subset of blocks, so cross-validation folds share the
    cached block means. Empty when the session has no rate to speak of.
    """
    if blocks.samples is None or blocks.samples.dv is None:
        return np.zeros(0)
    top = float(np.max(blocks.samples.abs_dv_means(), initial=0.0))
    if not top > 0:
        return np.zeros(0)
    return np.geomspace(KNEE_SHARES[0] * top, KNEE_SHARES[1] * top, KNEE_GRID_POINTS)


def lag_grid(session_duration_s: float) -> np.ndarray:
    """Lag time constants worth trying: from a few blocks to a third of the session."""
    return np.geomspace(5.0, max(20.0, session_duration_s / 3.0), LAG_GRID_POINTS)


def tau_grid(session_duration_s: float) -> np.ndarray:
    """Warm-up time constants worth trying: from seconds to beyond the session's length."""
    return np.geomspace(5.0, max(10.0, 3.0 * session_duration_s), TAU_GRID_POINTS)


def tau_groups(terms: tuple[Term, ...]) -> list[tuple[str, str | None]]:
    """The nonlinear parameters a fit estimates: the warm-up's τ, each lagged channel's τ and
    each rate-gated channel's knee."""
    groups: list[tuple[str, str | None]] = []
    for t in terms:
        key = WARMUP_GROUP if t.spec is TIME_WARMUP else (t.feature, t.channel)
        if t.spec in GROUPED and key not in groups:
            groups.append(key)
    return groups


def in_group(term: Term, group: tuple[str, str | None]) -> bool:
    return term.feature == group[0] and (group[0] == TIME_WARMUP.feature or term.channel == group[1])


def with_tau(terms: tuple[Term, ...], tau: float, group: tuple[str, str | None] = WARMUP_GROUP
             ) -> tuple[Term, ...]:
    """The group's parameter set to ``tau``: a time constant, or a gated group's knee (raw units)."""
    gated = group[0] == CHANNEL_GATED.feature
    return tuple(retimed(t, tau, gated) if in_group(t, group) else t for t in terms)


def group_tau(terms: tuple[Term, ...], group: tuple[str, str | None]) -> float | None:
    """The group's parameter in ``terms`` (a time constant, or a gated group's knee), if they have it."""
    gated = group[0] == CHANNEL_GATED.feature
    for p in (t.params for t in terms if in_group(t, group)):
        if gated and isinstance(p, Threshold):
            return float(p.threshold_raw)
        if not gated and isinstance(p, Tau):
            return float(p.tau_s)
    return None


def retimed(t: Term, tau: float, gated: bool = False) -> Term:
    """``t`` with its knee (a gated term) or its time constant set to ``tau``."""
    p = t.params
    if gated and isinstance(p, Threshold):
        return replace(t, params=replace(p, threshold_raw=tau))
    if not gated and isinstance(p, Tau):
        return replace(t, params=replace(p, tau_s=tau))
    raise TypeError(f"{t.describe()} has no {'knee' if gated else 'time constant'}")
