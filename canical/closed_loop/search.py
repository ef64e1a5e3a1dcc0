"""Close the loop: find what the rate model lacks, add it, and prove it on held-out data.

Starting from the fitted base model, each round scores every candidate
explanation (auxiliary channels and their transforms — level, derivative, lag,
direction of change —, warm-up, drift, direction of approach; and, as the
competing explanation, more capacity in the base model) by the rms error on
plateaus left out of the fit. The F-test's Bonferroni divisor counts every
candidate, so more transforms make each one harder to accept. A candidate is accepted only when

* it lowers the held-out rms by at least ``MIN_GAIN`` (relative), and by two
  standard errors of the rms estimate itself (about 1/sqrt(2·plateaus)), and
* a nested-model F-test on the training blocks, which charges it for its extra
  terms, rejects "no effect" at ``ALPHA`` divided by the number of candidates.

The winner's terms are pruned (a column stays only if leaving it out costs held-
out error), added, and the model is refitted jointly; rounds repeat until
nothing passes. When another candidate explains the same residual — it passes
alone, neither adds anything once the other is in, and the held-out plateaus
cannot tell which of the two predicts better — the two are reported as
*confounded*, with the session that would separate them, and one of them is
adopted all the same (the one the user names with ``prefer``, else by :func:`adopt`'s
rule): each corrects this session as well as the data allow, and leaving all out
would leave the whole residual in the set. The attribution is marked ambiguous in
the effect, the report and the set's ``fit`` record.
"Cannot tell" is a paired test over the held-out plateaus (Diebold–Mariano on
squared errors, plateaus in time order), at ``CONFOUND_ALPHA``; all candidates
are compared with every base size any of them needed, so that none loses to
another only because its own size search stopped short.
A channel's form is blamed only where it beats a drift of the session as flexible
(:func:`_drift_beats`), when it is accepted and again once every other effect is in
(:func:`drift_again`).
A channel's lag that ties with its level is the level (τ → 0), not a confound;
a warm-up that ties with a linear drift is the drift (τ → ∞).
What the loop leaves unexplained is judged afterwards (:mod:`canical.closed_loop.unexplained`).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace
from functools import partial
from typing import Any

import numpy as np
from scipy import optimize, special

from canical.calibrate.fit_points import FitPoints
from canical.calibrate.model_fit import ModelSpec, fit_model
from canical.calibrate.model_selection import ORDER_CHOICES, select_model
from canical.closed_loop.blocks import Blocks
from canical.closed_loop.candidates import (
    DRIFT_NAME,
    WARMUP_NAME,
    Candidate,
    bspline_basis,
    build_candidates,
    group_tau,
    knee_grid,
    lag_grid,
    plateau_means,
    shift_columns,
    tau_grid,
    tau_groups,
    untestable,
    with_tau,
)
from canical.closed_loop.drift_steps import change_times, merge_times, step_terms
from canical.closed_loop.findings import (
    Comparison,
    Confound,
    ConfoundCheck,
    Effect,
    Evidence,
    LoopStep,
    RoundRow,
    Score,
)
from canical.errors import CanicalError
from canical.models.piecewise import PiecewisePoly
from canical.models.segmented_inverse import JoinedDesign
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
    DIRECTION,
    TIME,
    TIME_WARMUP,
)
from canical.sets.term_params import Curve, OnChannel
from canical.sets.terms import Term, gated_name, spline_group

MIN_GAIN = 0.10
ALPHA = 1e-3
FOLDS = 5
PRUNE_TOLERANCE = 0.02
# One-sided level at which one explanation predicts the held-out plateaus better than another.
CONFOUND_ALPHA = 0.01
# A candidate whose held-out rms is this many times the best's does not explain the data as well,
# whatever the paired test says: its loss differences sit on a few plateaus (a warm-up's error is
# early), where the test has little power (seen: 14x the best's rms at p = 0.02).
TWIN_RMS_RATIO = 2.0
# At most this many choices of segment points for a new size, each on blocks corrected at the last.
KNOT_PASSES = 4


@dataclass(frozen=True)
class Structure:
    """The model being grown: base size, segment points and effect term templates."""

    spec: ModelSpec
    knots: np.ndarray
    scale: float
    span: tuple[float, float]
    terms: tuple[Term, ...] = ()

    @property
    def key(self) -> tuple[Any, ...]:
        """What tells structures apart for the :class:`Scorer`'s caches (the knots as a tuple:
        an array does not hash)."""
        return (self.spec, tuple(self.knots), self.terms)


@dataclass(frozen=True)
class Fit:
    poly: PiecewisePoly
    terms: tuple[Term, ...]  # with fitted coefficients (and τ)


GAUSS_NEWTON_STEPS = 4


def _solve(
    blocks: Blocks, s: Structure, terms: tuple[Term, ...], steps: int = GAUSS_NEWTON_STEPS,
    sensitivity: float | None = None, unshifted: JoinedDesign | None = None,
) -> tuple[PiecewisePoly, np.ndarray, float]:
    """Fit ω = f(ΔV − Σ c·column) jointly for the base model f and the coefficients c.

    The model is nonlinear in c (the effect shifts ΔV inside f), so it is solved by
    Gauss-Newton: at each step f is refitted on the shifted ΔV and c is corrected
    through the local slope of f. Effects are small next to the full scale, so a
    few steps converge. ``sensitivity`` and ``unshifted`` (the blocks' :func:`_mean_sensitivity`
    and :func:`_unshifted_design`), when a search solves on the same blocks many times: the
    first step's design is the unshifted ΔV's whatever the terms.
    """
    p = blocks.points
    cols = shift_columns(terms, blocks)
    coef = np.zeros(cols.shape[1])
    slope = np.full(len(p), 1.0 / (sensitivity or _mean_sensitivity(p)))
    steps = steps if terms else 1
    largest = np.max(np.abs(cols), axis=0) if steps > 1 else None
    shifted = p.dv - cols @ coef
    for step in range(steps):
        joined = unshifted if step == 0 and unshifted is not None else _design(blocks, s, shifted)
        fit = joined.fit(extra=-cols * slope[:, None])
        coef = coef + fit.extra
        shifted = p.dv - cols @ coef
        if largest is None or step == steps - 1 or np.max(np.abs(fit.extra * largest)) < 1e-6 * s.scale:
            break
        slope = fit.poly.slope(shifted)
    resid = p.rate - fit.poly.evaluate(shifted)[0]
    return fit.poly, coef, float(np.sum(p.weight * resid**2))


def _design(blocks: Blocks, s: Structure, dv: np.ndarray) -> JoinedDesign:
    """The structure's rate-model design on the blocks at ΔV ``dv`` (shifted by the effects)."""
    p = blocks.points
    return JoinedDesign.of(dv, p.rate, p.weight, s.knots, s.spec.order, scale=s.scale, span=s.span,
                           smoothness=s.spec.smoothness)


def _unshifted_design(blocks: Blocks, s: Structure) -> JoinedDesign:
    """The design every solve on these blocks and size starts from (:func:`_solve`'s first step)."""
    return _design(blocks, s, blocks.points.dv)


def _mean_sensitivity(p: FitPoints) -> float:
    """Counts per deg/s over the span: the first guess of the model's slope."""
    return float(np.polyfit(p.rate, p.dv, 1)[0]) or 1.0


def fit_structure(blocks: Blocks, s: Structure, duration_s: float, near: tuple[Term, ...] = ()) -> Fit:
    """Joint least squares of base model and terms; each time constant (warm-up, channel lag)
    by grid search on these blocks, one after the other. ``near``: fitted terms of the same
    structure on more blocks, whose time constants each search starts next to (:meth:`_TauSearch.best`)."""
    terms = s.terms
    sensitivity = _mean_sensitivity(blocks.points)
    unshifted = _unshifted_design(blocks, s)
    for group in tau_groups(terms):
        search = _TauSearch(blocks, replace(s, terms=terms), duration_s, group, sensitivity, unshifted)
        terms = with_tau(terms, search.best(group_tau(near, group)), group)
    poly, coef, _ = _solve(blocks, s, terms, sensitivity=sensitivity, unshifted=unshifted)
    return Fit(poly, tuple(replace(t, coefficient=float(c)) for t, c in zip(terms, coef, strict=True)))


@dataclass(frozen=True)
class _TauSearch:
    """τ of one group of terms (the warm-up, or one channel's lag), or a gated channel's knee, on
    these blocks: the best of a log grid, refined between its neighbours. ``sensitivity`` and
    ``unshifted``: the blocks' (:func:`_solve`), the same for every group and the final fit.

    A τ off by a grid step leaves an exponential-shaped residual that a drift
    term would then "explain" (for a lag: a derivative term); refining removes
    that false second effect.
    """

    blocks: Blocks
    s: Structure
    duration_s: float
    group: tuple[str, str | None]
    sensitivity: float
    unshifted: JoinedDesign

    @property
    def gated(self) -> bool:
        return self.group[0] == CHANNEL_GATED.feature

    @property
    def warmup(self) -> bool:
        return self.group[0] == TIME_WARMUP.feature

    def grid(self) -> np.ndarray:
        if self.gated:  # a knee in raw units, searched like a lag's τ
            return knee_grid(self.blocks)
        return tau_grid(self.duration_s) if self.warmup else lag_grid(self.duration_s)

    def rss(self, log_tau: float) -> float:
        """The fit's RSS at τ. A lag's τ is searched on the linearised fit (one Gauss-Newton step):
        its terms are small next to full scale, and there may be one lag per channel to search."""
        terms = with_tau(self.s.terms, float(np.exp(log_tau)), self.group)
        steps = GAUSS_NEWTON_STEPS if self.warmup else 1
        return _solve(self.blocks, self.s, terms, steps, self.sensitivity, self.unshifted)[2]

    def refined(self, lo: float, hi: float) -> float:
        """The best log τ between ``lo`` and ``hi`` (a warm-up's closer: its τ sets a whole exponential)."""
        xatol = 1e-3 if self.warmup else 1e-2
        res = optimize.minimize_scalar(self.rss, bounds=(lo, hi), method="bounded", options={"xatol": xatol})
        return float(res.x)

    def best(self, near: float | None = None) -> float:
        """The best τ. ``near``: where it was on more blocks (a cross-validation fold's τ beside the
        whole session's): the fold's RSS is taken at :data:`LOCAL_POINTS` τ spaced over a third of a
        grid step either side of there, and its best is the vertex of the parabola through the
        least and its neighbours; where the least is at either end, the search goes on past it
        (:meth:`beyond`), or, for a gated channel's knee, searches the whole grid.

        Why: each structure's score searches τ once per fold, and folds hold out a fifth of the
        plateaus, so their τ lies beside the whole session's. The points are the same in every
        fold, so a channel's lag at each is computed once for all five (a pass over the samples),
        where a refinement of its own tries τ no other fold does.
        """
        grid = np.log(self.grid())
        if near is None or not near > 0 or grid.size < 2:
            i = int(np.argmin([self.rss(t) for t in grid]))
            return float(np.exp(self.refined(grid[max(i - 1, 0)], grid[min(i + 1, grid.size - 1)])))
        local = np.log(near) + np.linspace(-1.0, 1.0, LOCAL_POINTS) * float(grid[1] - grid[0]) / 3.0
        rss = np.array([self.rss(t) for t in local])
        i = int(np.argmin(rss))
        if 0 < i < LOCAL_POINTS - 1:
            return float(np.exp(parabola_vertex(local[i - 1 : i + 2], rss[i - 1 : i + 2])))
        if self.gated:  # a knee's fit changes in steps as blocks cross it: local minima a walk stops in
            return self.best()
        outward = 1 if i else -1
        start = (local[i - outward], local[i]), (rss[i - outward], rss[i])
        return float(np.exp(self.beyond(start, bound=float(grid[-1] if i else grid[0]))))

    def beyond(self, start: tuple[tuple[float, float], tuple[float, float]], bound: float) -> float:
        """The least log τ past ``start`` (two points, log τ and RSS, the second the lower): steps
        outward from it, each twice the last, until the RSS rises (the vertex of the parabola through
        the last three points) or ``bound`` (the grid's end, which is then the best).

        Why not the whole grid: a fold's least lies a little past the local points (a fold whose RSS
        is flat in τ wanders there), where a step or two brackets it; searching the whole grid
        instead took a third of the loop's τ searches on a 2.8 h session.
        """
        (x_in, x), (y_in, y) = start
        step = x - x_in
        while (bound - x) * step > 0:
            nxt = x + step if (bound - x - step) * step > 0 else bound
            y_nxt = self.rss(nxt)
            if y_nxt > y:
                return parabola_vertex(np.array([x_in, x, nxt]), np.array([y_in, y, y_nxt]))
            (x_in, y_in), (x, y) = (x, y), (nxt, y_nxt)
            step *= 2.0
        return x if (bound - x) * step >= 0 else bound  # local points past the grid's end: its end


#: τ a fold's search tries about the whole session's (:meth:`_TauSearch.best`).
LOCAL_POINTS = 5


def parabola_vertex(x: np.ndarray, y: np.ndarray) -> float:
    """Where the parabola through three points (in order along x) whose middle is the least has its
    minimum (within the outer two; the middle where the three are level)."""
    (x0, x1, x2), (y0, y1, y2) = (float(v) for v in x), (float(v) for v in y)
    curvature = (y0 - y1) / (x0 - x1) / (x0 - x2) + (y2 - y1) / (x2 - x1) / (x2 - x0)
    if not curvature > 0:
        return x1
    slope = (y2 - y1) / (x2 - x1) - curvature * (x2 - x1)  # the parabola's slope at x1
    lo, hi = min(x0, x2), max(x0, x2)
    return float(np.clip(x1 - slope / (2.0 * curvature), lo, hi))


def predict(fit: Fit, blocks: Blocks) -> np.ndarray:
    """ω at each block: the base model on ΔV corrected by the fit's effect terms."""
    dv = blocks.points.dv
    if fit.terms:
        dv = dv - shift_columns(fit.terms, blocks) @ np.array([t.coefficient for t in fit.terms])
    return fit.poly.evaluate(dv)[0]


def effect_contribution(fit: Fit, blocks: Blocks, terms: tuple[Term, ...]) -> np.ndarray:
    """How much ``terms`` (a subset of the fit's) change the predicted rate at each block."""
    others = tuple(t for t in fit.terms if t not in terms)
    return predict(fit, blocks) - predict(Fit(fit.poly, others), blocks)


def plateau_folds(blocks: Blocks, k: int = FOLDS) -> list[np.ndarray]:
    """Held-out masks leaving whole plateaus out, interleaved in rate (plateaus of one rate in time
    order); the extreme rates always train.

    Why by rate: a fold must leave every segment of the rate model enough rates to be fitted. Taken
    in time order, a shuffled or repeated sweep can put most of a narrow segment's few rates in one
    fold, and that fold's fit of the segment is a guess (held-out errors of deg/s on a sensor whose
    model is right to 0.01). Every k-th plateau in rate order leaves out at most one of any k
    neighbouring rates; the plateaus of a rate (temperatures, sweeps) go to different folds.
    """
    plateaus = np.unique(blocks.plateau)
    rates = np.array([blocks.points.rate[blocks.plateau == p][0] for p in plateaus])
    edge = np.isin(rates, [rates.min(), rates.max()])
    inner = plateaus[~edge][np.argsort(rates[~edge], kind="stable")]
    k = max(2, min(k, inner.size))
    return [np.isin(blocks.plateau, inner[f::k]) for f in range(k)]


#: Stretches of the session a channel's form is tried on, fitted on the others (:func:`stretch_gain`).
STRETCHES = 4
#: The share of a stretch's held-out error a channel's form must remove to be blamed: a third, set on
#: the blind generator's development seeds, where forms fitted to a drift's wander and the weakest
#: real effects (another error large beside them) both come close to it; bench_blind scores it.
STRETCH_MIN_GAIN = 1.0 / 3.0
#: The share of the held-out error an equally flexible drift leaves that a channel's form must remove
#: on top of it to be blamed whatever its stretches say (:func:`_drift_beats`): a real effect of a
#: sensor that drifts too is still there once the drift is fitted; a form fitted to the drift's
#: wander has little left to take. The same third as :data:`STRETCH_MIN_GAIN`.
BEYOND_DRIFT_MIN_GAIN = 1.0 / 3.0


def stretch_folds(blocks: Blocks, k: int = STRETCHES) -> list[np.ndarray]:
    """Held-out masks leaving out contiguous stretches of the session, in time order; the extreme
    rates train every fold, as in :func:`plateau_folds`."""
    plateaus = np.unique(blocks.plateau)
    rates = np.array([blocks.points.rate[blocks.plateau == p][0] for p in plateaus])
    starts = np.array([blocks.time_s[blocks.plateau == p].min() for p in plateaus])
    edge = np.isin(rates, [rates.min(), rates.max()])
    inner = plateaus[~edge][np.argsort(starts[~edge], kind="stable")]
    return [np.isin(blocks.plateau, chunk) for chunk in np.array_split(inner, k)]


def judged_stretches(blocks: Blocks, folds: list[np.ndarray]) -> list[np.ndarray] | None:
    """Of each stretch held out, the blocks whose rate the other stretches also hold (the rate model
    does not extrapolate there); None where that leaves fewer than half of the stretches' blocks."""
    rate = np.round(blocks.points.rate, 6)
    judged = [held & np.isin(rate, rate[~held]) for held in folds]
    if sum(int(m.sum()) for m in judged) < 0.5 * sum(int(m.sum()) for m in folds):
        return None
    return judged


def stretch_gain(blocks: Blocks, s: Structure, terms: tuple[Term, ...], duration_s: float) -> float | None:
    """The share of the held-out error of stretches of the session that adding ``terms`` to ``s``
    removes, each stretch predicted by the whole model (coefficients and time constants) fitted on
    the other stretches: the larger of the pooled share and the median stretch's. None where too
    few plateaus can be judged.

    Only plateaus whose rate the other stretches also hold are judged: a stretch of time is also a
    part of the table's sweep, and at a rate no other stretch has the rate model would extrapolate,
    with or without the terms. The pooled share weighs the stretches where the error is; the median
    ignores one whose channel goes beyond what the others saw (a spline extrapolating).
    """
    folds = stretch_folds(blocks)
    judged = judged_stretches(blocks, folds)
    if judged is None:
        return None
    before = held_out_errors(blocks, s, folds, duration_s)
    after = held_out_errors(blocks, replace(s, terms=s.terms + terms), folds, duration_s)
    every = np.any(judged, axis=0)
    pooled = 1.0 - rms(after[every]) / rms(before[every])
    each = [1.0 - rms(after[m]) / rms(before[m]) for m in judged if np.any(m)]
    return float(max(pooled, np.median(each)))


#: Shifts of a channel against the sensor whose stretch gain a form's own must beat where the
#: stretches alone would blame it (:func:`shifted_stretch_gain`): 19, a rank test at 5 %.
SHIFTS = 19
#: The shifts span this part of the channel followed by its reverse (fractions of the session's
#: length; 0 and 2 are the channel itself): a channel shifted by a little is still in step with the
#: sensor wherever it changes slowly.
SHIFT_SPAN = (0.2, 1.8)
#: Shares of error removed closer than this are a tie: a share of one that the channel and its shifts
#: all reach is the stretches' own misfit (a base model extrapolating), taken by any form alike.
SHARE_RESOLUTION = 1e-6
#: A shift whose copy correlates with the channel this closely (block means, either sign) is the
#: channel again, not a copy out of step with the sensor: a cycling chamber shifted by about its
#: period. It says nothing of chance and is not counted.
SAME_CHANNEL_CORRELATION = 0.95


def _on_channel(term: Term, channel: str) -> Term:
    """``term`` read of another channel."""
    if not isinstance(term.params, OnChannel):
        raise TypeError(f"{term.describe()} reads no channel")
    return replace(term, params=replace(term.params, channel=channel))


def shifted_stretch_gain(blocks: Blocks, s: Structure, cand: Candidate, duration_s: float) -> float:
    """The largest :func:`stretch_gain` ``cand``'s form takes of its channel shifted in time against
    the sensor (:meth:`Blocks.with_shifted`), over :data:`SHIFTS` shifts evenly spread over
    :data:`SHIFT_SPAN`; -inf where none can be judged.

    Why: stretches of a session fitted on the others are few (:data:`STRETCHES`), and two slowly
    wandering records, a channel that random-walks and a sensor's bias that random-walks or steps,
    predict each other's stretches by chance (seen: shares of 0.37-0.78 taken by forms of a channel
    the sensor did not follow, on 9 sessions of the blind generator, against a bar of a third).
    The channel shifted keeps its own wander and loses its step with the sensor: a share no shift
    reaches is the sensor's, not chance's. A shift that brings a cycling channel back in phase with
    itself (:data:`SAME_CHANNEL_CORRELATION`) is skipped: it is the channel, and takes the
    channel's own share (seen: a lag of a cycling chamber taking 0.55 of the stretches, its copy one
    period on 0.63 at correlation 0.97, every other copy at most 0.32).
    """
    ch = cand.channel or ""
    best = -np.inf
    for i, fraction in enumerate(np.linspace(*SHIFT_SPAN, SHIFTS)):
        name = f"{ch} shifted {i}"
        shifted = blocks.with_shifted(ch, name, float(fraction))
        if not out_of_step(blocks.aux[ch], shifted.aux[name]):
            continue
        terms = tuple(_on_channel(t, name) for t in cand.terms)
        gain = stretch_gain(shifted, s, terms, duration_s)
        if gain is not None:
            best = max(best, gain)
    return float(best)


def out_of_step(channel: np.ndarray, copy: np.ndarray) -> bool:
    """Whether a shifted ``copy`` of a channel (block means) is no copy of it in another guise:
    correlated with it less than :data:`SAME_CHANNEL_CORRELATION`, either sign (a form fits the
    channel upside down as well). A constant channel's copy is the channel."""
    with np.errstate(invalid="ignore", divide="ignore"):
        r = float(np.corrcoef(channel, copy)[0, 1])
    return bool(np.isfinite(r) and abs(r) < SAME_CHANNEL_CORRELATION)


#: A drift's basis function counts on the blocks where it reaches this (B-splines, 0 to 1): one that
#: lives only in a stretch held out has nothing to be fitted on there.
DRIFT_SUPPORT = 1e-3
#: The share of what a stretch's own drift leaves that a form fitted on the other stretches must
#: remove there to be blamed beyond the drift (:func:`stretch_beyond_drift_gain`): any. A form fitted
#: to this session's wander carries nothing into a stretch it did not see, and then only adds its
#: own scatter (a share below zero).
BEYOND_STRETCH_MIN_GAIN = 0.0


def stretch_beyond_drift_gain(blocks: Blocks, s: Structure, terms: tuple[Term, ...],
                              drift: tuple[Term, ...], duration_s: float) -> float | None:
    """The share of what a drift of each stretch of the session leaves that ``terms`` remove there,
    the model (``drift`` in, on the stretches it reaches) fitted on the other stretches: the larger
    of the pooled share and the median stretch's, as in :func:`stretch_gain`. None where too few
    plateaus can be judged.

    A stretch's held-out errors, with and without ``terms``, are each taken less their weighted
    least-squares fit of a constant and the drift's basis functions that reach the stretch: any
    smooth function of the session's clock there, as flexible as the drift is over the session.

    Why: the held-out plateaus of :class:`BeyondDrift`'s gain lie between the ones the form is fitted
    on, so a flexible form of a channel that wanders (a smoothed lag, τ free), fitted to what a
    random-walking bias leaves beyond the drift, predicts them as well (seen: half of what the drift
    left, at p = 2e-4, by a distractor that random-walks). Fitted on other stretches, such a form
    has nothing to carry into this one; a sensor's own effect has.
    """
    folds = stretch_folds(blocks)
    judged = judged_stretches(blocks, folds)
    if judged is None:
        return None
    basis = shift_columns(drift, blocks)
    before: list[np.ndarray] = []
    after: list[np.ndarray] = []
    for held, m in zip(folds, judged, strict=True):
        if not m.any():
            continue
        reached = np.max(np.abs(basis[~held]), axis=0) > DRIFT_SUPPORT
        nuisance = replace(s, terms=s.terms + tuple(t for t, r in zip(drift, reached, strict=True) if r))
        without = held_out_errors(blocks, nuisance, [held], duration_s)[m]
        with_terms = held_out_errors(blocks, replace(nuisance, terms=nuisance.terms + terms), [held],
                                     duration_s)[m]
        local, weight = basis[m], blocks.points.weight[m]
        before.append(_less_local_drift(without, local, weight))
        after.append(_less_local_drift(with_terms, local, weight))
    pooled = 1.0 - rms(np.concatenate(after)) / rms(np.concatenate(before))
    each = [1.0 - rms(a) / rms(b) for a, b in zip(after, before, strict=True)]
    return float(max(pooled, np.median(each)))


def _less_local_drift(errors: np.ndarray, basis: np.ndarray, weight: np.ndarray) -> np.ndarray:
    """``errors`` less their weighted least-squares fit of a constant and the columns of ``basis``
    that reach these blocks (:data:`DRIFT_SUPPORT`)."""
    x = np.column_stack([np.ones(errors.size), basis[:, np.max(np.abs(basis), axis=0) > DRIFT_SUPPORT]])
    root = np.sqrt(weight)
    coef = np.linalg.lstsq(x * root[:, None], errors * root, rcond=None)[0]
    return errors - x @ coef


def held_out_errors(blocks: Blocks, s: Structure, folds: list[np.ndarray], duration_s: float,
                    near: tuple[Term, ...] = ()) -> np.ndarray:
    """Each block's error against a model fitted without its plateau; NaN at blocks in no fold.

    Why NaN: the extreme rates train every fold (:func:`plateau_folds`), so they have no held-out
    error; a zero there would enter every rms and plot as a perfect prediction (2-3 % too good on
    a typical session). They are judged apart, in sample (:func:`extreme_rates_rms`).

    ``near``: the structure's terms fitted on every block. Each fold's time constants are searched
    within a third of a grid step of theirs (over the whole grid where a fold's least lies at either
    end, :meth:`_TauSearch.best`): the held-out plateaus place where a fold's search looks, the
    fold's own blocks choose τ and every coefficient.
    """
    errors = np.full(len(blocks), np.nan)
    for held in folds:
        fit = fit_structure(blocks.take(~held), s, duration_s, near)
        errors[held] = predict(fit, blocks.take(held)) - blocks.points.rate[held]
    return errors


def rms(e: np.ndarray) -> float:
    """The rms of the errors there are: blocks with no held-out error (NaN) do not count."""
    e = e[np.isfinite(e)]
    return float(np.sqrt(np.mean(e**2))) if e.size else float("nan")


def extreme_rates_rms(fit: Fit, blocks: Blocks, folds: list[np.ndarray]) -> float | None:
    """The in-sample rms at the blocks no fold holds out (the extreme rates): a model fitted
    without them would extrapolate its end segments, which says nothing of the set, so they are
    reported apart from the held-out figure, with the caveat that they are in the fit."""
    extreme = ~np.any(folds, axis=0)
    if not extreme.any():
        return None
    return rms(predict(fit, blocks.take(extreme)) - blocks.points.rate[extreme])


@dataclass
class Scorer:
    """Held-out rms and training RSS of structures, cached by their terms and size."""

    blocks: Blocks
    folds: list[np.ndarray]
    duration_s: float
    cache: dict[Any, Score] = field(default_factory=dict)
    losses: dict[Any, np.ndarray] = field(default_factory=dict)
    fits: dict[Any, Fit] = field(default_factory=dict)
    held_errors: dict[Any, np.ndarray] = field(default_factory=dict)
    resized: dict[Any, Structure] = field(default_factory=dict)

    def fit(self, s: Structure) -> Fit:
        """The structure fitted to every block, once: the search asks for the same fit from
        several places (a size chosen again, its score, the round's record), each τ search a
        tenth of a second on a long session."""
        key = s.key
        if key not in self.fits:
            self.fits[key] = fit_structure(self.blocks, s, self.duration_s)
        return self.fits[key]

    def score(self, s: Structure) -> Score:
        """Held-out rms, training RSS of plateau-mean residuals, number of coefficients."""
        key = s.key
        if key not in self.cache:
            fit = self.fit(s)
            err = held_out_errors(self.blocks, s, self.folds, self.duration_s, fit.terms)
            resid = self.blocks.points.rate - predict(fit, self.blocks)
            n_par = (len(s.knots) + 1) * (s.spec.order + 1) + len(s.terms)
            self.cache[key] = Score(rms(err), plateau_rss(self.blocks, resid), n_par)
            self.losses[key] = plateau_losses(self.blocks, self.folds, err)
            self.held_errors[key] = err
        return self.cache[key]

    def errors(self, s: Structure) -> np.ndarray:
        """Each block's held-out error (:func:`held_out_errors`; NaN at the extreme rates)."""
        self.score(s)
        return self.held_errors[s.key]

    def held_rms(self, s: Structure) -> float:
        """The structure's held-out rms, deg/s: what the loop ranks by."""
        return self.score(s).held_out_rms_dps

    def plateau_loss(self, s: Structure) -> np.ndarray:
        """Sum of squared held-out block errors of each held-out plateau, in time order."""
        self.score(s)
        return self.losses[s.key]

    @property
    def n_plateaus(self) -> int:
        return int(np.unique(self.blocks.plateau).size)


def plateau_losses(blocks: Blocks, folds: list[np.ndarray], err: np.ndarray) -> np.ndarray:
    """Per held-out plateau, the sum of its blocks' squared held-out errors (plateau order = time).

    Their total over plateaus is what the held-out rms is made of, so a paired test
    on them compares exactly what the loop ranks candidates by.
    """
    held = np.any(folds, axis=0)
    _, idx = np.unique(blocks.plateau[held], return_inverse=True)
    return np.bincount(idx, err[held] ** 2)


def better_p(a: np.ndarray, b: np.ndarray) -> float:
    """One-sided p-value that losses ``a`` are smaller than ``b`` on average (paired by plateau).

    Diebold–Mariano: the mean loss difference over its standard error, the variance
    taken with a Bartlett (Newey–West) window over neighbouring plateaus, because a
    slow effect leaves errors of plateaus close in time alike.
    """
    d = np.asarray(b, dtype=float) - np.asarray(a, dtype=float)
    n = d.size
    if n < 3:
        return 1.0
    c = d - d.mean()
    lags = int(np.floor(n ** (1.0 / 3.0)))
    var = float(c @ c) / n
    for k in range(1, lags + 1):
        var += 2.0 * (1.0 - k / (lags + 1)) * float(c[k:] @ c[:-k]) / n
    if var <= 0.0:
        return 0.0 if d.mean() > 0 else 1.0
    return float(special.stdtr(n - 1, -d.mean() / np.sqrt(var / n)))  # Student's t upper tail


def plateau_rss(blocks: Blocks, resid: np.ndarray) -> float:
    """Weighted RSS of per-plateau mean residuals.

    Blocks of one plateau share its table-rate error and slow disturbances, so
    they are not independent; the F-test counts plateaus, not blocks.
    """
    _, idx = np.unique(blocks.plateau, return_inverse=True)
    w = np.bincount(idx, blocks.points.weight)
    mean = np.bincount(idx, blocks.points.weight * resid) / w
    return float(np.sum(w * mean**2))


def f_test(small: Score, big: Score, n: int) -> tuple[float, float]:
    """Nested-model F statistic and p-value (RSS from weighted least squares)."""
    k = max(big.n_par - small.n_par, 1)
    dof = max(n - big.n_par, 1)
    f = ((small.training_rss - big.training_rss) / k) / max(big.training_rss / dof, 1e-300)
    return float(f), float(special.fdtrc(k, dof, f))  # F upper tail


def recommend(a: Candidate, b: Candidate) -> str:
    """The session that would tell two confounded explanations apart."""
    kinds = {a.kind, b.kind}
    names = {c.kind: c for c in (a, b)}
    if kinds == {CHANNEL, TIME} and names[CHANNEL].terms[0].spec in (CHANNEL_DERIVATIVE, CHANNEL_LAG,
                                                                    CHANNEL_DIRECTION):
        ch = names[CHANNEL].channel
        return (
            f"record a session that cycles {ch} up and down after the sensor is warm (powered on long "
            f"before the first plateau), so that changes of {ch} no longer follow time since power-on"
        )
    if kinds == {CHANNEL, TIME}:
        ch = names[CHANNEL].channel
        return (
            f"record a session in which {ch} does not follow time since power-on: soak the sensor "
            f"before powering it on, then step {ch} up and down in random order"
        )
    if kinds == {CHANNEL} and a.channel == b.channel:
        return (f"record a session in which {a.channel} changes at several speeds and holds between "
                "changes, so its level, its rate of change and its direction of change separate")
    if kinds == {CHANNEL}:
        return f"record a session in which {a.channel} and {b.channel} are varied independently"
    if DIRECTION in kinds:
        return "record a session that approaches each rate from above and below, in random order"
    return "record a longer session with several power cycles, so warm-up and drift separate"


@dataclass
class LoopResult:
    """What the loop found, for the coefficient set, the report and the plots."""

    fit: Fit
    structure: Structure
    blocks: Blocks
    base_fit: Fit
    effects: list[Effect]
    confounded: list[Confound]
    rounds: list[list[RoundRow]]
    rms_before: float
    rms_after: float
    errors_before: np.ndarray
    errors_after: np.ndarray
    capacity_changes: list[str]
    # In-sample rms of the final fit at the extreme rates, which train every fold (see held_out_errors).
    extreme_rms: float | None = None
    untestable: dict[str, float] = field(default_factory=dict)
    # Each change to the model in order, with the held-out error after it (same scheme throughout),
    # so a report can be read from the rate model alone down to the set that was written.
    steps: list[LoopStep] = field(default_factory=list)
    candidates: list[Candidate] = field(default_factory=list)  # every candidate built, for the residual
    # Session times (s) at which the bias jumped, taken out where a channel's form met the drift.
    bias_jumps_s: tuple[float, ...] = ()


def _step(scorer: Scorer, s: Structure, what: str) -> LoopStep:
    return LoopStep(what, s.spec.describe(), len(s.terms), scorer.held_rms(s))


def _capacity_options(s: Structure) -> list[ModelSpec]:
    out = [replace(s.spec, n_segments=s.spec.n_segments + 1)]
    if s.spec.order < 4:
        out.append(replace(s.spec, order=s.spec.order + 1))
    return out


def corrected_points(blocks: Blocks, fit: Fit) -> FitPoints:
    """The blocks with the fit's effects taken out of ΔV: what the base model alone should fit."""
    p = blocks.points
    if not fit.terms:
        return p
    shift = shift_columns(fit.terms, blocks) @ np.array([t.coefficient for t in fit.terms])
    return FitPoints(p.rate, p.dv - shift, p.weight, p.dv_sem)


def reselect_size(scorer: Scorer, s: Structure) -> Structure:
    """Once an effect is in, choose the base size again: the effect may have hidden what it needs.
    Once per structure: a round's winner is chosen again when its confounds are weighed."""
    if s.key not in scorer.resized:
        scorer.resized[s.key] = _reselected(scorer, s)
    return scorer.resized[s.key]


def _reselected(scorer: Scorer, s: Structure) -> Structure:
    corrected = corrected_points(scorer.blocks, scorer.fit(s))
    try:
        spec, _ = select_model(corrected, s.spec, orders=loop_orders(s.spec), high_orders=())
    except CanicalError:
        return s
    resized = _with_spec(scorer, s, spec)
    if resized is None or scorer.held_rms(resized) >= scorer.held_rms(s):
        return s
    return resized


def loop_orders(spec: ModelSpec) -> tuple[int, ...]:
    """The orders the loop may choose the base size among: the first round's, and the base's own.

    Why not the higher ones: once effects come in, a higher order fits part of what an effect
    left (the demo's own set came out worse that way); the base chose a higher order
    only where the rate alone needed it.
    """
    return tuple(sorted({*ORDER_CHOICES, spec.order}))


def _with_spec(scorer: Scorer, s: Structure, spec: ModelSpec) -> Structure | None:
    """Re-choose segment points for a new base size, on blocks corrected by the terms.

    The terms' coefficients were fitted with the old size: when that was too small
    they carry some of its misfit, and segment points chosen on blocks corrected by
    them can be far off (seen: held-out error 80× a model told the effect's). So the points are
    chosen again on blocks corrected by the fit at the new size, until they settle.
    """
    current = s
    for _ in range(KNOT_PASSES if s.terms else 1):
        corrected = corrected_points(scorer.blocks, scorer.fit(current))
        try:
            fitted = fit_model(corrected, spec)
        except (CanicalError, np.linalg.LinAlgError):  # a size the data cannot support: no candidate
            return None if current is s else current
        if fitted.spec.n_segments != spec.n_segments:
            return None if current is s else current
        assert isinstance(fitted.model, PiecewisePoly)  # the loop's base is segmented-inverse
        knots = np.asarray(fitted.model.knots, dtype=float)
        if current is not s and np.array_equal(knots, current.knots):
            break
        current = replace(s, spec=spec, knots=knots)
    return current


# Rounds of the search: each scores every candidate and a bigger base, accepts at most one.
MAX_ROUNDS = 12


@dataclass(frozen=True)
class _Bar:
    """What a candidate must beat to be accepted: the relative held-out gain and the F-test level."""

    min_gain: float
    alpha: float


def _judge(scorer: Scorer, current: Score, s: Structure, name: str, bar: _Bar) -> RoundRow:
    """One row of a round's table: the structure's score against the current model, and the verdict."""
    sc = scorer.score(s)
    f, p = f_test(current, sc, scorer.n_plateaus)
    ok = sc.held_out_rms_dps < current.held_out_rms_dps * (1 - bar.min_gain) and p < bar.alpha
    return RoundRow(name, sc.held_out_rms_dps, f, p, bool(ok))


def _score_round(
    scorer: Scorer, s: Structure, pool: list[Candidate], bar: _Bar
) -> tuple[list[RoundRow], list[tuple[float, str, Candidate | Structure]]]:
    """Every candidate and every bigger base on the current model: the table, and those that pass."""
    current = scorer.score(s)
    options: list[tuple[str, Structure, Candidate | Structure]] = [
        (cand.name, replace(s, terms=s.terms + cand.terms), cand) for cand in pool
    ]
    for cap in _capacity_options(s):
        bigger = _with_spec(scorer, s, cap)
        if bigger is not None:
            options.append((f"capacity:{cap.describe()}", bigger, bigger))
    table = [_judge(scorer, current, st, name, bar) for name, st, _ in options]
    passing = [(row.held_out_rms_dps, row.candidate, what)
               for row, (_, _, what) in zip(table, options, strict=True) if row.passes]
    passing.sort(key=lambda x: x[0])
    return table, passing


def _base_before_channel(
    scorer: Scorer, passing: list[tuple[float, str, Candidate | Structure]], bar: _Bar
) -> tuple[str, Candidate | Structure]:
    """The round's pick: the best that passes, but a channel's form only where it also passes on
    the best bigger base that passes, else that base.

    Why: what a base too small leaves (a bend of the rate curve) is a pattern over the session
    that a flexible channel form can follow as well as one more segment can; blamed on the
    channel, it would go to the vehicle as a bias that follows the channel. A real effect of the
    channel is still there on the bigger base. Seen: on a 2.8 h session of a sensor whose bias
    follows temp_c alone, a rate-gated temp_c term 0.4 % ahead of a sixth segment.
    """
    _, name, best = passing[0]
    bases = [(n, b) for _, n, b in passing if isinstance(b, Structure)]
    if not isinstance(best, Candidate) or best.kind != CHANNEL or not bases:
        return name, best
    base_name, base = bases[0]
    on_base = replace(base, terms=base.terms + best.terms)
    if _judge(scorer, scorer.score(base), on_base, best.name, bar).passes:
        return name, best
    return base_name, base


#: How the loop picks one of a confounded group when the user named none (see :func:`adopt`).
ADOPTION_RULE = ("adopted by rule: a form of time since power-on before a channel's, then the "
                 "fewest fitted parameters, then the lower held-out error")


def adopt(scorer: Scorer, s: Structure, group: list[Candidate]) -> Candidate:
    """The explanation of a confounded group the set carries: each removes the residual on this
    session equally well (held-out plateaus cannot tell them apart), so leaving all out would leave
    the whole residual in the user's set, while any one of them corrects it.

    Why this order: a channel is blamed only where it beats time, since a slow drift and a slowly
    varying channel look alike and a channel term blamed for drift adds a bias that follows the
    channel on the vehicle; time since power-on is measured on the vehicle too. Then the fewest
    fitted parameters (columns that pay, and each time constant or knee searched): the simpler
    form extrapolates less beyond what the session showed (a transient's rate of change against
    a spline of its lag). Then the lower held-out rms on the base size each deserves.
    """

    def key(c: Candidate) -> tuple[int, int, float]:
        terms = _prune(scorer, s, c).terms
        n_par = len(terms) + len(tau_groups(terms))
        return (int(c.kind == CHANNEL), n_par, scorer.held_rms(replace(s, terms=s.terms + terms)))

    return min(group, key=key)


#: An ambiguous correction is written when it at least halves the held-out error: a smaller gain
#: that several forms share is as likely this session's own wander (flicker, a rate random walk)
#: as an effect of the sensor, and a clean sensor's set must not carry it.
ADOPT_MIN_GAIN = 0.5


def _adopted_if_large(scorer: Scorer, s: Structure, before: Score,
                      group: list[Candidate]) -> tuple[Candidate | None, str]:
    """The rule's choice among a confounded group (:func:`adopt`), if it removes enough of the
    residual, or if every form of the group is one channel's.

    Why one channel's forms need no such share: the group then disagrees on the form only, not on
    the cause, and whether the channel's effect is this session's wander instead is what the
    session's drift decides next (:func:`_drift_beats`, every channel's adopted form meets it),
    where a form fitted to a wander meets an equally flexible function of time. Left out, the
    residual stays in the set (a transient under ramps: 13x the noise floor, twice a model told it).
    """
    candidate = adopt(scorer, s, group)
    with_it = replace(s, terms=s.terms + _pruned(scorer, s, candidate).terms)
    gain = 1.0 - scorer.held_rms(with_it) / before.held_out_rms_dps
    if gain >= ADOPT_MIN_GAIN:
        return candidate, ADOPTION_RULE
    if _one_channel(group):
        return candidate, (f"{ADOPTION_RULE}; it removes {gain:.0%} of the held-out error, less than "
                           f"half, and every form is {candidate.channel}'s: the session's drift judged it")
    alone = alone_beyond_drift(scorer, s, group)
    if alone is not None:
        return alone, (f"the only channel's form that stands out on top of a drift of the session as "
                       f"flexible (the group removes {gain:.0%} of the held-out error, less than half; "
                       "the other channels' forms are as likely the session's wander)")
    return None, (f"none adopted: the rule's choice, {candidate.name}, removes {gain:.0%} of the "
                  "held-out error, less than half: as likely the session's wander as an effect")


def alone_beyond_drift(scorer: Scorer, s: Structure, group: list[Candidate]) -> Candidate | None:
    """Of a confounded group of two channels' forms or more (and nothing else), the form that adds
    most on top of a drift of the session as flexible as itself (:class:`BeyondDrift` at
    :data:`CONFOUND_ALPHA` shared among the group, each with the bias jumps it finds, and a share of
    the stretches beyond their drift of :data:`STRETCH_MIN_GAIN` or more), where the forms that do
    are all one channel's; None otherwise.

    Why: a form of a channel that random-walks beside the sensor (a distractor's smoothed lag)
    predicts the held-out plateaus of a sensor whose bias wanders as well as a real effect of
    another channel does, and the tie left the real effect out of the set where the pair removed
    less than half of the error (seen: a level of temperature steps, 43 %). On top of the drift
    the real effect stands out and the wander's form does not. The plateaus cannot tell the twins
    apart, so the stretches decide, by the bar they meet where they alone decide against the drift
    (:func:`instead_of_drift`): a lag of temperature steps on a sensor whose bias stepped with them
    stood out on top of the drift at p = 1e-6 and carried 0.08 into the stretches; the level of
    case 73 carried 0.39. Only this way: a form that merely predicts stretches better than the drift
    (:func:`instead_of_drift`) did so by chance on three of 160 drifting sensors with no channel
    effect once it was asked of every twin. A form of time in the group is a drift itself: the group
    then stays as it was.
    """
    if any(c.kind != CHANNEL for c in group) or len({c.channel for c in group}) < 2:
        return None
    alpha = CONFOUND_ALPHA / len(group)
    standing: list[tuple[float, Candidate]] = []
    for cand in group:
        drift = drift_competitor(cand, scorer.blocks)
        if drift is None:
            continue
        base = replace(s, terms=s.terms + jump_terms(scorer.blocks, bias_jumps(scorer, s, cand)))
        beyond = _beyond_drift(scorer, _Footing(scorer, base, [cand, drift]), cand, drift, alpha)
        if beyond.passes(alpha) and beyond.stretches is not None and beyond.stretches >= STRETCH_MIN_GAIN:
            standing.append((beyond.gain, cand))
    if len({c.channel for _, c in standing}) != 1:
        return None
    return max(standing, key=lambda gc: gc[0])[1]


def _one_channel(group: list[Candidate]) -> bool:
    """Whether every candidate of the group is a form of the same channel."""
    return all(c.kind == CHANNEL for c in group) and len({c.channel for c in group}) == 1


#: The pseudo-channel of the session's own clock (block mean times) the drift competitor is a spline of.
SESSION_CLOCK = "session clock"
DRIFT_SPLINE_NAME = "drift of the session (smooth in time)"


def drift_competitor(cand: Candidate, blocks: Blocks) -> Candidate | None:
    """A smooth function of the session's clock as flexible as a channel's candidate: as many
    interior knots (evenly spaced in time) as its spline has, and one more for a time constant it
    searches; one for a form without a spline (a cubic with one knot: four coefficients against a
    level's three or a lag's two and its τ).

    Why: a spline of a slowly varying channel, or its lag with τ free, fits any slow drift of the
    sensor (a bias random walk) about as well as the channel's real effect would; time's own forms
    on the list (warm-up, linear drift) are far stiffer, so they lost the comparison and the drift
    was blamed on the channel. Against a form of time as flexible, the channel must show that it
    is the channel the sensor follows. None when the session has no span of time.
    """
    t = blocks.time_s
    if not np.ptp(t) > 0:
        return None
    first = cand.terms[0]
    # A spline's time constant searched (a smoothed lag's τ) is one more parameter: one more knot.
    searched = len(tau_groups(cand.terms))
    interior = max(1, len(first.params.knots) - 2 + searched) if isinstance(first.params, Curve) else 1
    basis = bspline_basis(np.linspace(float(t.min()), float(t.max()), 64), interior, even=True)
    if basis is None:
        return None
    breaks, pieces = basis
    terms = tuple(Term.of(CHANNEL_SPLINE, "bias", 0.0, channel=SESSION_CLOCK, knots=breaks, pieces=p)
                  for p in pieces[1:])
    return Candidate(DRIFT_SPLINE_NAME, TIME, None, terms)


#: Channel forms whose effect depends on the rate too (a rate-gated or rate-shaped term, a
#: direction's): a drift of the sensor's bias shifts every rate alike and cannot take their place.
RATE_SHAPED = (CHANNEL_GATED, CHANNEL_RATE_SPLINE, CHANNEL_DIRECTION)


def _has_bias(cand: Candidate) -> bool:
    """Whether a candidate has a bias that follows its channel alone: what a bias drift can mimic."""
    return any(t.form == "bias" and t.spec not in RATE_SHAPED for t in cand.terms)


def instead_of_drift(*, r_channel: float, r_drift: float, p: float, gain: float | None,
                     by_chance: Callable[[], float] | None = None) -> bool:
    """Whether a channel's form is blamed instead of an equally flexible drift (:func:`_drift_beats`'s
    way 1): it predicts the held-out plateaus better (held-out rms ``r_channel`` against ``r_drift``,
    ``p`` the paired one-sided p-value of that), and, if it has a bias of the channel alone, the
    stretches of the session it was not fitted on (their share of error removed, ``gain``): by
    :data:`STRETCH_MIN_GAIN`, or by any share where the plateaus' win is significant at
    :data:`CONFOUND_ALPHA`. A drift whose held-out rms is :data:`TWIN_RMS_RATIO` times the
    channel's or more does not explain the data as well, whatever the test and the stretches say.

    Why the second: a sensor whose bias also stepped leaves the stretches misfit whatever the
    channel's form (seen: a lag the sensor followed removed a quarter of the stretches' error and
    beat the drift at p = 0.005); a form fitted to a drift's wander, beside it, never beat the drift
    significantly on the plateaus (160 development seeds of the blind generator's drift class:
    least p 0.011, with a share of the stretches below zero). Why the ratio: a transient of a
    channel that steps sits on the few plateaus after each step, where the paired test has little
    power and a stretch holds one or two steps (seen: the drift's rms 3.7 times the channel's at
    p = 0.048, a quarter of the stretches' error removed); against a form fitted to a drift's wander,
    the drift's rms was at most 1.27 times the form's (those 160 seeds).

    Where the stretches' share alone decides, it must beat ``by_chance()``, the share the same form
    takes of its channel shifted against the sensor (:func:`shifted_stretch_gain`; called only
    there). Why: a slowly wandering channel predicts the stretches of a sensor whose bias wanders
    or steps by chance: on those 160 seeds 5 forms were blamed on the stretches alone (shares of
    0.37-0.72), and in 3 of them the channel's shifts took as much.
    """
    if not r_channel < r_drift:
        return False
    if r_drift >= TWIN_RMS_RATIO * r_channel:
        return True
    if gain is None or (p < CONFOUND_ALPHA and gain > 0.0):
        return True
    return gain >= STRETCH_MIN_GAIN and (by_chance is None or gain > by_chance() + SHARE_RESOLUTION)


def _drift_beats(scorer: Scorer, s: Structure, best: Candidate) -> Confound | None:
    """The record of a channel's candidate that the session's own drift explains as well; None
    when the channel is the better explanation (or the candidate is not a channel's).

    A channel is blamed in either of two ways. (1) It predicts the held-out plateaus better than
    an equally flexible drift of the session (:func:`drift_competitor`), and, if it has a bias of
    the channel alone (a form that depends on the rate too is no bias drift's double), it predicts
    stretches of the session it was not fitted on (:func:`stretch_gain`): the sensor follows its
    channel the same way all session long, while a drift does not repeat. (2) Added on top of that
    drift, it still removes a large share of the held-out error, significantly
    (:data:`BEYOND_DRIFT_MIN_GAIN`, paired at :data:`CONFOUND_ALPHA`): the effect of a sensor that
    also drifts, whose stretches the drift keeps from being predicted, or whose form extrapolates
    badly into a stretch whose channel goes beyond the others'. A spline of a slowly varying
    channel fits a slow drift about as well as the channel's real effect would; once the drift
    is fitted, such a form has little left to take.

    The three models compared are each on the base size they deserve (:class:`_Footing`): on a base
    too small for the sensor, the rate model's misfit dominates every held-out error and ties the
    channel with the drift (a temperature effect that hid the curvature the first size choice needed).

    The drift is not added either way: a smooth function of this session's clock is a property of
    the session, not of the sensor, and on the vehicle it would add this session's wander at the
    same times after power-on. What is left is reported (unexplained, if it is large).
    """
    if best.kind != CHANNEL:
        return None
    drift = drift_competitor(best, scorer.blocks)
    if drift is None:
        return None
    footing = _Footing(scorer, s, [best, drift])
    with_channel, with_drift = footing.of(best.terms, footing.own[best.name]), footing.of(drift.terms)
    r_channel, r_drift = scorer.held_rms(with_channel), scorer.held_rms(with_drift)
    beyond = _beyond_drift(scorer, footing, best, drift, CONFOUND_ALPHA)
    if beyond.passes(CONFOUND_ALPHA):
        return None
    gain = stretch_gain(scorer.blocks, s, best.terms, scorer.duration_s) if _has_bias(best) else None
    p = better_p(scorer.plateau_loss(with_channel), scorer.plateau_loss(with_drift))
    by_chance = partial(shifted_stretch_gain, scorer.blocks, s, best, scorer.duration_s)
    if instead_of_drift(r_channel=r_channel, r_drift=r_drift, p=p, gain=gain, by_chance=by_chance):
        return None
    ch = best.channel or ""
    return Confound(
        candidates=(best.name, DRIFT_SPLINE_NAME), weaker_alternatives=(),
        held_out_rms_dps={best.name: r_channel, DRIFT_SPLINE_NAME: r_drift},
        paired_p={DRIFT_SPLINE_NAME: p}, paired_alpha=CONFOUND_ALPHA,
        held_out_rms_before_dps=scorer.held_rms(s), resolved_by_user=None,
        recommendation=(f"record a session in which {ch} changes in steps in random order, so that it "
                        "no longer follows the sensor's slow drift"),
        adopted=None, adoption_rule=f"drift, confounded with {ch}", drift_of_session=True,
        stretch_gain=gain, beyond_drift_gain=beyond.gain, beyond_drift_stretch_gain=beyond.stretches,
    )


@dataclass(frozen=True)
class BeyondDrift:
    """What a channel's form adds on top of an equally flexible drift of the session: the share of
    the drift's held-out error it removes, the paired p of that gain, and, where those pass and the
    form has a bias of the channel alone, the share it predicts of stretches it was not fitted on
    beyond their own drift (:func:`stretch_beyond_drift_gain`; None otherwise)."""

    gain: float
    p: float
    stretches: float | None = None

    def passes(self, alpha: float) -> bool:
        """:meth:`large` at ``alpha``, and a share of the stretches above
        :data:`BEYOND_STRETCH_MIN_GAIN` where it was judged."""
        return self.large(self.gain, self.p, alpha) and (
            self.stretches is None or self.stretches > BEYOND_STRETCH_MIN_GAIN)

    @staticmethod
    def large(gain: float, p: float, alpha: float) -> bool:
        """A large share (:data:`BEYOND_DRIFT_MIN_GAIN`), significant at ``alpha``; or a share that
        leaves the drift's held-out rms :data:`TWIN_RMS_RATIO` times the pair's or more, whatever
        the test says.

        Why the second: the same as :func:`instead_of_drift`'s ratio. A transient of a channel that
        steps, on a sensor whose bias steps too, sits on the few plateaus after each step, where
        the paired test has little power (seen: three quarters of the drift's error removed at
        p = 0.0126 and 0.0105); a form fitted to a drift's wander removed at most 0.41 of it (the
        blind generator's 160 development seeds of drifting sensors, 487 such judgements:
        ``tests/benchmarks/why_drift.py``). A distractor's smoothed lag on a sensor whose bias
        random-walks removed 0.51: the stretches' share then decides (:meth:`passes`).
        """
        return gain >= 1.0 - 1.0 / TWIN_RMS_RATIO or (gain >= BEYOND_DRIFT_MIN_GAIN and p < alpha)


def _beyond_drift(scorer: Scorer, footing: _Footing, cand: Candidate, drift: Candidate,
                  alpha: float) -> BeyondDrift:
    """:class:`BeyondDrift` of ``cand`` over ``drift``, each on the base size it deserves; the
    stretches judged only where the gain passes at ``alpha`` (eight fits, each τ searched)."""
    with_drift, with_both = footing.of(drift.terms), footing.of(drift.terms + cand.terms)
    r_drift = scorer.held_rms(with_drift)
    gain = 1.0 - scorer.held_rms(with_both) / r_drift
    p = better_p(scorer.plateau_loss(with_both), scorer.plateau_loss(with_drift))
    if not (BeyondDrift.large(gain, p, alpha) and _has_bias(cand)):
        return BeyondDrift(gain, p)
    base = replace(with_drift, terms=footing.s.terms)
    return BeyondDrift(gain, p, stretch_beyond_drift_gain(scorer.blocks, base, cand.terms, drift.terms,
                                                          scorer.duration_s))


def beyond_the_drift(scorer: Scorer, s: Structure, forms: list[Candidate]) -> Candidate | None:
    """Of a channel's other forms, once its best has lost to the session's drift, the one that
    adds most on top of a drift as flexible as itself, where that passes :func:`_drift_beats`'s
    second rule at :data:`CONFOUND_ALPHA` shared among the forms tried; None when none does.

    Why: the form that best predicts held-out plateaus on its own is the one that best follows
    the drift (a smoothed lag of a cycling chamber fits bias steps); a transient the chamber's
    changes cause is another form of the same channel, which no smooth drift of the session can
    take, and it was never tried once the channel lost.
    """
    pairs = [(form, drift) for form in forms if (drift := drift_competitor(form, scorer.blocks)) is not None]
    alpha = CONFOUND_ALPHA / max(len(pairs), 1)
    tried = [(_beyond_drift(scorer, _Footing(scorer, s, [form, drift]), form, drift, alpha), form)
             for form, drift in pairs]
    passing = [(b.gain, form) for b, form in tried if b.passes(alpha)]
    return max(passing, key=lambda gf: gf[0])[1] if passing else None


@dataclass(frozen=True)
class Removed:
    """An accepted effect that lost to the session's drift once the others were in: its record, and
    the model once it was taken out (for the loop's steps)."""

    name: str
    record: Confound
    structure: Structure


@dataclass(frozen=True)
class DriftAgain:
    """The structure once each accepted effect has met the session's drift again with the others in
    (:func:`drift_again`): the effects removed, in order, and the bias jumps judged with them."""

    structure: Structure
    removed: tuple[Removed, ...]
    jumps_s: tuple[float, ...]


def drift_again(scorer: Scorer, s: Structure, accepted: list[Candidate],
                prefer: tuple[str, ...] = ()) -> DriftAgain:
    """Each accepted channel effect judged against the session's drift once more (:func:`_drift_beats`),
    now on the structure with every other accepted effect in, in the order they were accepted; one
    that loses is taken out (and the base size chosen again) before the next is judged. Nothing to do
    with fewer than two effects, or for a form the user named (``prefer``); nor for a channel with
    two forms in, each of which can stand in for the other (its level beside its spline), and each
    of which met the drift when it went in.

    Why: each effect met the drift on what the effects before it left. A form of a channel that
    itself wanders can stand in, early, for part of a real effect found later (a smoothed lag of a
    random-walking channel took a level effect under ramps, and beat the drift on top of it); once
    the real effect is in, it explains nothing a drift of the session does not, and in the set it
    would add that channel's wander on the vehicle. The same rule on the same evidence, with the
    others in: backward elimination of the forward search's choices.
    """
    removed: list[Removed] = []
    jumps_s: tuple[float, ...] = ()
    if len(accepted) < 2:
        return DriftAgain(s, (), ())
    kept = list(accepted)
    for cand in accepted:
        if cand.name in prefer or cand.kind != CHANNEL or _channel_count(kept, cand.channel) > 1:
            continue
        mine = {id(t) for t in cand.terms}  # the same objects: the structure is grown of them
        without = replace(s, terms=tuple(t for t in s.terms if id(t) not in mine))
        if len(without.terms) != len(s.terms) - len(cand.terms):
            raise AssertionError(f"{cand.name}: its columns are not the structure's")
        jumps = bias_jumps(scorer, without, cand)
        with_jumps = replace(without, terms=without.terms + jump_terms(scorer.blocks, jumps))
        drift = _drift_beats(scorer, with_jumps, cand)
        if drift is None:
            continue
        others = [c.name for c in kept if c is not cand]
        was = "was" if len(others) == 1 else "were"
        record = replace(drift, adoption_rule=f"{drift.adoption_rule}, once {', '.join(others)} {was} in")
        kept.remove(cand)
        jumps_s = merged_jumps(jumps_s, jumps, scorer.blocks)
        s = reselect_size(scorer, without)
        removed.append(Removed(cand.name, record, s))
    return DriftAgain(s, tuple(removed), jumps_s)


def _channel_count(cands: list[Candidate], channel: str | None) -> int:
    """How many of ``cands`` are forms of ``channel``."""
    return sum(c.kind == CHANNEL and c.channel == channel for c in cands)


def _lost_to_drift(c: Confound) -> Confound:
    """A group whose adopted form then lost to the session's drift: none of it is in the set."""
    return replace(c, adopted=None, adoption_rule=(
        f"{c.adoption_rule}; then none: {c.adopted} does not beat a drift of the session as flexible"))


def _judged_again(c: Confound, accepted: str, after: str) -> Confound:
    """A group none of which was adopted, whose member ``accepted`` stood out once ``after`` was in."""
    if c.adopted is not None or c.drift_of_session or accepted not in c.candidates:
        return c
    first = c.adoption_rule.removeprefix("none adopted: ")
    return replace(c, adopted=accepted, adoption_rule=(
        f"at first none ({first}); judged again once {after} was in, {accepted} stood out of what "
        "was left"))


def bias_jumps(scorer: Scorer, s: Structure, best: Candidate) -> tuple[float, ...]:
    """The times the bias jumped, where a channel's candidate is to meet the session's drift
    (:func:`_drift_beats` judges channel and drift with :func:`jump_terms` in both): found per
    plateau in what ``s`` and the smooth drift leave (a slow drift or effect bends there, a jump
    stays), where no channel jumps. Empty for a candidate that is not a channel's."""
    drift = drift_competitor(best, scorer.blocks) if best.kind == CHANNEL else None
    if drift is None:
        return ()
    s = replace(s, terms=s.terms + drift.terms)
    blocks = scorer.blocks
    residual = predict(scorer.fit(s), blocks) - blocks.points.rate
    channels = tuple(plateau_means(blocks, v) for name, v in blocks.aux.items() if name != SESSION_CLOCK)
    return change_times(plateau_means(blocks, blocks.time_s), plateau_means(blocks, residual), channels)


def jump_terms(blocks: Blocks, times: tuple[float, ...]) -> tuple[Term, ...]:
    """A bias step of the session's clock at each of ``times`` (never written into a set)."""
    return step_terms(times, float(blocks.time_s.min()), float(blocks.time_s.max()), SESSION_CLOCK)


def merged_jumps(known: tuple[float, ...], found: tuple[float, ...], blocks: Blocks) -> tuple[float, ...]:
    """``known`` and the new times of ``found`` (:func:`merge_times`, within a plateau's spacing)."""
    times = np.sort(plateau_means(blocks, blocks.time_s))
    return merge_times(known, found, float(np.median(np.diff(times))) if times.size > 1 else 0.0)


def _confound(check: ConfoundCheck, before: Score, chosen: Candidate | None, rule: str) -> Confound:
    """The report's record of a confounded group: who, how close, and the session that separates them."""
    group = [check.best, *check.twins]
    return Confound(
        candidates=tuple(c.name for c in group),
        weaker_alternatives=tuple(c.name for c in check.shadows),
        held_out_rms_dps={c.name: check.evidence[c.name].held_out_rms_dps for c in group},
        paired_p={c.name: check.evidence[c.name].p_best_better for c in check.twins},
        paired_alpha=CONFOUND_ALPHA,
        held_out_rms_before_dps=before.held_out_rms_dps,
        resolved_by_user=chosen.name if chosen is not None and rule.endswith("(--prefer)") else None,
        # the pair across families first: separating those needs a different session
        recommendation=recommend(check.best, next((c for c in check.twins if c.kind != check.best.kind),
                                                  check.twins[0])),
        adopted=None if chosen is None else chosen.name,
        adoption_rule=rule,
    )


def _effect(cand: Candidate, before: Score, after: Score, f: float, p: float, bar: _Bar,
            terms: tuple[Term, ...]) -> Effect:
    """The record of an accepted effect, with the terms as fitted when it was added."""
    evidence = Evidence(held_out_gain=1.0 - after.held_out_rms_dps / before.held_out_rms_dps,
                        min_gain=bar.min_gain, f_statistic=f, p_value=p, alpha=bar.alpha)
    return Effect(kind=cand.kind, channel=cand.channel, name=cand.name, evidence=evidence,
                  terms=terms, rms_before_dps=before.held_out_rms_dps,
                  rms_after_dps=after.held_out_rms_dps)


def _key(t: Term) -> tuple[Any, ...]:
    """What tells a fitted term from the others (a spline's basis functions share all but their pieces)."""
    pieces = t.params.pieces if isinstance(t.params, Curve) else None
    return (t.kind, t.channel, t.feature, t.form, t.reference, pieces)


def _final_effects(effects: list[Effect], final_fit: Fit) -> list[Effect]:
    """The effects with the final joint coefficients of the terms that stayed, and readable names.

    An effect none of whose terms stayed is left out.
    """
    final_terms = {_key(t): t for t in final_fit.terms}
    out = []
    for eff in effects:
        terms = tuple(final_terms[k] for k in map(_key, eff.terms) if k in final_terms)
        if terms:
            out.append(replace(eff, terms=terms, description=_describe_effect(eff, final_fit)))
    return out


def _describe_effect(eff: Effect, final_fit: Fit) -> str:
    """A readable name with the final time constant: lag(temp_c, τ=140 s), temp_c × (|rate| > 30 dps)."""
    lagged = [t for t in final_fit.terms if t.channel == eff.channel
              and t.spec is (CHANNEL_LAG_SPLINE if eff.name.startswith("smooth(lag(") else CHANNEL_LAG)]
    gated = [t for t in final_fit.terms if t.channel == eff.channel and CHANNEL_GATED.owns(t)]
    is_lag = lagged and eff.name.startswith(("lag(", "smooth(lag("))
    description = lagged[0].describe() if is_lag else eff.name
    if gated and eff.name == gated_name(eff.channel or ""):
        description = gated_name(eff.channel or "", knee_dps(final_fit.poly, gated[0].params.threshold_raw))
    return description


def run_loop(
    blocks: Blocks,
    spec: ModelSpec,
    knots: np.ndarray,
    scale: float,
    span: tuple[float, float],
    duration_s: float,
    *,
    prefer: tuple[str, ...] = (),
    progress=lambda _msg: None,
) -> LoopResult:
    """Grow the model until no candidate explanation passes; see the module docstring."""
    folds = plateau_folds(blocks)
    # The session's own clock as a pseudo-channel of block means, for the drift a channel's form
    # must beat (see _drift_beats); no candidate is built of it.
    blocks = replace(blocks, aux={**blocks.aux, SESSION_CLOCK: blocks.time_s})
    scorer = Scorer(blocks, folds, duration_s)
    s = Structure(spec, np.asarray(knots, dtype=float), scale, span)
    pool = [c for c in build_candidates(blocks, duration_s) if c.channel != SESSION_CLOCK]
    every_candidate = list(pool)
    tied = untestable(pool, blocks)
    if tied:
        progress(f"not testable here (follow the table rate): {', '.join(tied)}")
    pool = [c for c in pool if c.name not in tied]
    n_candidates = len(pool) + 2
    bar = _Bar(min_gain=max(MIN_GAIN, 2.0 / np.sqrt(2.0 * scorer.n_plateaus)),
               alpha=ALPHA / max(n_candidates, 1))
    base_score = scorer.score(s)
    effects: list[Effect] = []
    confounded: list[Confound] = []
    rounds: list[list[RoundRow]] = []
    capacity_changes: list[str] = []
    steps = [_step(scorer, s, "rate model alone")]
    shelved: list[Candidate] = []  # a confounded group none of which was adopted
    restored: dict[str, str] = {}  # a shelved candidate: the effect whose acceptance restored it
    jumps_s: tuple[float, ...] = ()  # times the bias jumped (bias_jumps), for the report
    accepted: list[Candidate] = []  # each accepted effect as its columns went in, in order
    for _round in range(MAX_ROUNDS):
        current = scorer.score(s)
        progress(f"round {len(rounds) + 1}: held-out rms {current.held_out_rms_dps:.4f} deg/s, "
                 f"{len(pool)} candidates")
        table, passing = _score_round(scorer, s, pool, bar)
        rounds.append(table)
        if not passing:
            break
        best_name, best = _base_before_channel(scorer, passing, bar)
        if isinstance(best, Structure):
            capacity_changes.append(best_name)
            s = best
            steps.append(_step(scorer, s, f"base model grown to {s.spec.describe()}"))
            continue
        # Every candidate, not only those that passed at the current base size: with its
        # own best base size a candidate may turn out to explain the same residual.
        check = _confounded_with(scorer, s, best, pool, bar.min_gain)
        best = check.best
        twins: tuple[str, ...] = ()
        if check.twins:
            group = [best, *check.twins]
            chosen = next((c for c in group if c.name in prefer), None)
            rule = "named by the user (--prefer)" if chosen else ADOPTION_RULE
            if chosen is None:
                chosen, rule = _adopted_if_large(scorer, s, current, group)
            confounded.append(_confound(check, current, chosen, rule))
            # Shadows explain a part of the same residual: accepting one later would be a guess too.
            pool = [c for c in pool if c not in group and c not in check.shadows]
            if chosen is None:
                progress(f"confounded {' / '.join(c.name for c in group)}: none adopted ({rule})")
                shelved += [c for c in group if c.name not in restored]
                continue
            twins = tuple(c.name for c in group if c is not chosen)
            progress(f"confounded {' / '.join(c.name for c in group)}: adopted {chosen.name} ({rule})")
            best = chosen
        jumps = () if best.name in prefer else bias_jumps(scorer, s, best)
        jumps_s = merged_jumps(jumps_s, jumps, blocks)
        # The bias jumped where no channel did: channel and drift are judged with the jumps in both.
        with_jumps = replace(s, terms=s.terms + jump_terms(blocks, jumps))
        drift = None if best.name in prefer else _drift_beats(scorer, with_jumps, best)
        if drift is not None:
            if twins:  # the group's record: its choice is not in the set
                confounded[-1] = _lost_to_drift(confounded[-1])
            confounded.append(drift)
            progress(f"{best.name} does not beat a drift of the session as flexible: not blamed")
            forms = [c for c in pool if c.channel == best.channel and c is not best]
            pool = [c for c in pool if c.channel != best.channel]
            beyond = beyond_the_drift(scorer, with_jumps, forms)
            if beyond is None:
                continue
            progress(f"{beyond.name} explains what a drift of the session leaves: blamed instead")
            best, twins = beyond, ()  # not one of the group that lost: no ambiguity of its own
        pruned = _pruned(scorer, s, best)
        accepted.append(pruned)
        s_new = replace(s, terms=s.terms + pruned.terms)
        after = scorer.score(s_new)
        f, p = f_test(current, after, scorer.n_plateaus)
        fit_now = scorer.fit(s_new)
        effects.append(replace(_effect(best, current, after, f, p, bar, fit_now.terms[len(s.terms) :]),
                               ambiguous_with=twins))
        if best.name in restored:
            confounded = [_judged_again(c, best.name, restored[best.name]) for c in confounded]
        progress(f"accepted {best.name}: held-out rms {current.held_out_rms_dps:.4f} -> "
                 f"{after.held_out_rms_dps:.4f} deg/s")
        steps.append(_step(scorer, s_new, f"added {best.name}"))
        s = reselect_size(scorer, s_new)
        if s is not s_new:
            steps.append(_step(scorer, s, "base size chosen again with the effect in"))
        pool = [c for c in pool if c is not best]
        # A group none of which removed half the error may, once this effect is in, stand out of
        # what is left: each is judged again, once (a lag under a sensor's linear drift).
        pool += shelved
        restored |= {c.name: best.name for c in shelved}
        shelved = []
    again = drift_again(scorer, s, accepted, prefer)
    for gone in again.removed:
        effects = [e for e in effects if e.name != gone.name]
        progress(f"{gone.name} does not beat a drift of the session as flexible once the other effects "
                 "are in: removed")
        steps.append(_step(scorer, gone.structure, f"removed {gone.name}: a drift explains it as well"))
        confounded.append(gone.record)
    jumps_s = merged_jumps(jumps_s, again.jumps_s, blocks)
    s = again.structure
    pruned_all = _prune_all(scorer, s)
    if len(pruned_all.terms) != len(s.terms):
        steps.append(_step(scorer, pruned_all, "terms that no longer pay removed"))
    s = pruned_all
    final_fit = scorer.fit(s)
    base_s = Structure(spec, np.asarray(knots, dtype=float), scale, span)
    return LoopResult(
        fit=final_fit,
        structure=s,
        blocks=blocks,
        base_fit=scorer.fit(base_s),
        effects=_final_effects(effects, final_fit),
        confounded=confounded,
        rounds=rounds,
        rms_before=base_score.held_out_rms_dps,
        rms_after=scorer.held_rms(s),
        errors_before=scorer.errors(base_s),
        errors_after=scorer.errors(s),
        capacity_changes=capacity_changes,
        extreme_rms=extreme_rates_rms(final_fit, blocks, folds),
        untestable=tied,
        steps=steps,
        candidates=every_candidate,
        bias_jumps_s=jumps_s,
    )


class _Footing:
    """Structures on the base size each explanation deserves, for :func:`_confounded_with`.

    An explanation's footing is the best (by held-out rms) of its own size chosen again with it
    in and of every size another hopeful explanation needed.
    """

    def __init__(self, scorer: Scorer, s: Structure, hopeful: list[Candidate]) -> None:
        self.scorer, self.s = scorer, s
        self.own = {c.name: reselect_size(scorer, self.with_terms(c.terms))
                    for c in hopeful}
        self.sizes = list(dict.fromkeys(st.spec for st in self.own.values()))

    def with_terms(self, terms: tuple[Term, ...]) -> Structure:
        return replace(self.s, terms=self.s.terms + terms)

    def of(self, terms: tuple[Term, ...], first: Structure | None = None) -> Structure:
        """The terms on the best of their own size and every size a hopeful candidate needed."""
        options = [first or reselect_size(self.scorer, self.with_terms(terms))]
        for spec in self.sizes:
            if spec != options[0].spec:
                other = _with_spec(self.scorer, self.with_terms(terms), spec)
                options += [other] if other is not None else []
        return min(options, key=self.scorer.held_rms)


def _confounded_with(
    scorer: Scorer, s: Structure, best: Candidate, pool: list[Candidate], min_gain: float
) -> ConfoundCheck:
    """The best explanation and the candidates that explain the same residual, with the evidence.

    Each explanation is scored with the base size it deserves (an under-sized base
    leaves misfit that would blur the comparison): its own size chosen again with it
    in, or any size another explanation needed, whichever predicts held-out plateaus
    better — otherwise one candidate can lose only because its coefficient, fitted
    with a base model too small, hid the misfit that the size search needed to see.
    The best is chosen again on that footing. Another candidate explains the same
    residual when adding it on top of the best does not gain both ``min_gain`` and
    a significant paired improvement (the loop's own bar for a second effect). It is
    a *twin* — the data cannot tell them apart — when the best neither predicts the
    held-out plateaus significantly better than it alone nor adds significantly on
    top of it; a *shadow* otherwise. Significance is :func:`better_p` at
    ``CONFOUND_ALPHA``: no fixed ratio of errors, so a pair is called confounded
    exactly when the plateau-to-plateau scatter of held-out errors allows either.
    """
    held_rms = scorer.held_rms
    r_now = held_rms(s)
    # A candidate that gains nothing at the current size is not re-scored with its own
    # size (that costs a model selection each); one that gains a little might still tie.
    hopeful = [c for c in pool
               if c is best or held_rms(replace(s, terms=s.terms + c.terms)) < r_now * (1 - min_gain / 2)]
    footing = _Footing(scorer, s, hopeful)
    alone = {c.name: footing.of(c.terms, footing.own[c.name]) for c in hopeful}
    useful = [c for c in hopeful if held_rms(alone[c.name]) < r_now * (1 - min_gain)] or [best]
    best = min(useful, key=lambda c: held_rms(alone[c.name]) if c.name in alone else r_now)
    best = _simplest_paid(best, useful, alone, held_rms, min_gain)
    best_s = alone.get(best.name, footing.with_terms(best.terms))
    check = ConfoundCheck(best, evidence={best.name: Comparison(held_rms(best_s), 0.5)})
    _sort_twins(scorer, footing, check, best_s, [c for c in useful if c is not best], alone, min_gain)
    _prefer_level(scorer, check, alone)
    for nested in [c for c in check.twins if _nests(c, check.best) or any(_nests(c, o) for o in check.twins)]:
        check.twins.remove(nested)
        check.shadows.append(nested)
    return check


def _simplest_paid(best: Candidate, useful: list[Candidate], alone: dict[str, Structure],
                   held_rms: Callable[[Structure], float], min_gain: float) -> Candidate:
    """The best, or the best of the simpler forms it nests when it does not beat them by the loop's
    own bar for an effect (``min_gain``): a smooth coefficient in rate that predicts 4 % better
    than the channel's plain level has not shown that its extra shape is there."""
    if best.name not in alone:
        return best
    bar = held_rms(alone[best.name]) / (1 - min_gain)
    simpler = [c for c in useful if c.name in alone and _nests(best, c) and held_rms(alone[c.name]) <= bar]
    return min(simpler, key=lambda c: held_rms(alone[c.name])) if simpler else best


def _sort_twins(scorer: Scorer, footing: _Footing, check: ConfoundCheck, best_s: Structure,
                others: list[Candidate], alone: dict[str, Structure], min_gain: float) -> None:
    """Each other useful candidate: a later round's (it adds to the best), a twin or a shadow."""
    held_rms = scorer.held_rms
    loss_best = scorer.plateau_loss(best_s)

    def adds(both: Structure, base: Structure) -> bool:
        """Does the pair predict clearly and significantly better than ``base`` alone?"""
        return (held_rms(both) < held_rms(base) * (1 - min_gain)
                and better_p(scorer.plateau_loss(both), scorer.plateau_loss(base)) < CONFOUND_ALPHA)

    for other in others:
        other_s = alone[other.name]
        both = footing.of(check.best.terms + other.terms)
        if adds(both, best_s):  # it explains something more: a later round judges it on its own
            continue
        p_best = better_p(loss_best, scorer.plateau_loss(other_s))
        check.evidence[other.name] = Comparison(held_rms(other_s), p_best)
        twin = (p_best >= CONFOUND_ALPHA and held_rms(other_s) <= TWIN_RMS_RATIO * held_rms(best_s)
                and not adds(both, other_s))
        (check.twins if twin else check.shadows).append(other)


def _prefer_level(scorer: Scorer, check: ConfoundCheck, alone: dict[str, Structure]) -> None:
    """A channel's level is its lag with τ → 0 (a drift is a warm-up with τ → ∞): when the two
    tie, the data do not need the time constant, and the simpler one is the answer; the other
    twins are then judged against it."""
    level = next((c for c in check.twins if _nests(check.best, c)), None)
    if level is None:
        return
    check.twins.remove(level)
    check.shadows.append(check.best)
    check.best = level
    held_rms = scorer.held_rms
    loss_level = scorer.plateau_loss(alone[level.name])
    for c in list(check.twins):
        check.with_p(c.name, better_p(loss_level, scorer.plateau_loss(alone[c.name])))
        far = held_rms(alone[c.name]) > TWIN_RMS_RATIO * held_rms(alone[level.name])
        if check.evidence[c.name].p_best_better < CONFOUND_ALPHA or far:
            check.twins.remove(c)
            check.shadows.append(c)


def _nests(general: Candidate, simple: Candidate) -> bool:
    """True when ``simple`` is ``general`` in a limit (a channel's level is its lag at τ → 0,
    and its rate-gated form at knee → 0; a linear drift is a warm-up at τ → ∞); a smooth form
    holds what a spline with knots everywhere holds: a channel's smooth form its level and
    square, its smooth coefficient in rate its level and its rate-gated level, the smooth form of
    its lag the lag, the smooth form of the level and the level, that of its rate of change the rate."""
    if general.name == WARMUP_NAME and simple.name == DRIFT_NAME:
        return True
    if general.kind != CHANNEL or simple.kind != CHANNEL or general.channel != simple.channel:
        return False
    return simple.name in _simpler_forms(general.name, general.channel or "")


def _simpler_forms(name: str, channel: str) -> tuple[str, ...]:
    """The candidates of ``channel`` that the candidate ``name`` holds in a limit."""
    level = CHANNEL_OFFSET.label(channel)
    lag = CHANNEL_LAG.label(channel)
    nested = {
        lag: (level,),
        gated_name(channel): (level,),
        CHANNEL_SPLINE.label(channel): (level,),
        CHANNEL_RATE_SPLINE.label(channel): (level, gated_name(channel)),
        CHANNEL_LAG_SPLINE.label(channel): (level, lag, CHANNEL_SPLINE.label(channel)),
        CHANNEL_DERIVATIVE_SPLINE.label(channel): (CHANNEL_DERIVATIVE.label(channel),),
    }
    return nested.get(name, ())


def knee_dps(poly: PiecewisePoly, knee_raw: float | None) -> float:
    """A knee in raw units as a rate: the mean |ω| the model gives at ΔV = ±knee."""
    k = float(knee_raw or 0.0)
    w = poly.evaluate(np.array([-k, k]))[0]
    return float(np.mean(np.abs(w)))


def _drop_unpaid(
    scorer: Scorer, s: Structure, fixed: tuple[Term, ...], terms: tuple[Term, ...]
) -> tuple[Term, ...]:
    """Drop columns of ``terms`` (kept on top of ``fixed``) one at a time while held-out error
    does not suffer by more than ``PRUNE_TOLERANCE``; at least one stays.

    A spline's basis columns go or stay together (:func:`_units`): one basis function less is
    another shape, with a hole where its knots are, not a simpler one.
    """

    def held(kept: list[tuple[Term, ...]]) -> float:
        return scorer.held_rms(replace(s, terms=fixed + tuple(t for unit in kept for t in unit)))

    units = _units(terms)
    while len(units) > 1:
        full = held(units)
        fewer = [units[:i] + units[i + 1 :] for i in range(len(units))]
        best_rms, i = min((held(f), i) for i, f in enumerate(fewer))
        if best_rms > full * (1 + PRUNE_TOLERANCE):
            break
        units = fewer[i]
    return tuple(t for unit in units for t in unit)


def _units(terms: tuple[Term, ...]) -> list[tuple[Term, ...]]:
    """The terms as the units pruning drops: each term alone, a spline's basis (same kind,
    channel, form, reference and knots) as one, in the order the terms come."""
    units: dict[Any, tuple[Term, ...]] = {}
    for j, t in enumerate(terms):
        key = spline_group(t) if t.spec.needs_spline else j
        units[key] = (*units.get(key, ()), t)
    return list(units.values())


def _prune_all(scorer: Scorer, s: Structure) -> Structure:
    """With the final base size, drop any accepted column that no longer earns its keep."""
    return replace(s, terms=_drop_unpaid(scorer, s, (), s.terms))


def _pruned(scorer: Scorer, s: Structure, cand: Candidate) -> Candidate:
    """The candidate's columns that pay, pruned on the current base and on the base chosen again
    with the candidate in; where the two differ, the set whose structure, sized again, predicts
    the held-out plateaus better. Why both: on a base too small for the effect a column that
    only pays once the base fits is dropped for good (a knee's scale terms), while a column that
    pays only on the larger base may leave the next size choice worse off."""
    here = _prune(scorer, s, cand)
    sized = reselect_size(scorer, replace(s, terms=s.terms + cand.terms))
    there = _prune(scorer, replace(sized, terms=s.terms), cand)
    if there.terms == here.terms:
        return here

    def resized(c: Candidate) -> float:
        return scorer.held_rms(reselect_size(scorer, replace(s, terms=s.terms + c.terms)))

    return min((here, there), key=resized)


def _prune(scorer: Scorer, s: Structure, cand: Candidate) -> Candidate:
    """Drop the candidate's columns one at a time while held-out error does not suffer."""
    return cand.with_terms(_drop_unpaid(scorer, s, s.terms, cand.terms))
