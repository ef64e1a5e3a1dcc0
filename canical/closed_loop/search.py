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
alone, yet neither adds anything once the other is in — the two are reported as
*confounded*, with the session that would separate them, and neither is added
unless the user names one with ``prefer``: a guess would be wrong in the field.
A channel's lag that ties with its level is the level (τ → 0), not a confound.
What the loop leaves unexplained is judged afterwards (:mod:`canical.closed_loop.unexplained`).
"""

from __future__ import annotations

from dataclasses import dataclass, field, replace
from typing import Any

import numpy as np
from scipy import optimize, stats

from canical.calibrate.fit_points import FitPoints
from canical.calibrate.model_fit import ModelSpec, fit_model
from canical.calibrate.model_selection import select_model
from canical.closed_loop.blocks import Blocks
from canical.closed_loop.candidates import (
    Candidate,
    build_candidates,
    knee_grid,
    lag_grid,
    shift_columns,
    tau_grid,
    tau_groups,
    untestable,
    with_tau,
)
from canical.errors import CanicalError
from canical.models.piecewise import PiecewisePoly
from canical.models.segmented_inverse import fit_segmented_inverse
from canical.sets.terms import Term, gated_name

MIN_GAIN = 0.10
ALPHA = 1e-3
FOLDS = 5
PRUNE_TOLERANCE = 0.02


@dataclass(frozen=True)
class Structure:
    """The model being grown: base size, segment points and effect term templates."""

    spec: ModelSpec
    knots: np.ndarray
    scale: float
    span: tuple[float, float]
    terms: tuple[Term, ...] = ()


@dataclass(frozen=True)
class Fit:
    poly: PiecewisePoly
    terms: tuple[Term, ...]  # with fitted coefficients (and τ)


GAUSS_NEWTON_STEPS = 4


def _solve(
    blocks: Blocks, s: Structure, terms: tuple[Term, ...], steps: int = GAUSS_NEWTON_STEPS
) -> tuple[PiecewisePoly, np.ndarray, float]:
    """Fit ω = f(ΔV − Σ c·column) jointly for the base model f and the coefficients c.

    The model is nonlinear in c (the effect shifts ΔV inside f), so it is solved by
    Gauss-Newton: at each step f is refitted on the shifted ΔV and c is corrected
    through the local slope of f. Effects are small next to the full scale, so a
    few steps converge.
    """
    p = blocks.points
    cols = shift_columns(terms, blocks)
    coef = np.zeros(cols.shape[1])
    slope = np.full(len(p), 1.0 / _mean_sensitivity(p))
    for _ in range(steps if terms else 1):
        dv = p.dv - cols @ coef
        fit = fit_segmented_inverse(
            dv,
            p.rate,
            p.weight,
            s.knots,
            s.spec.order,
            scale=s.scale,
            span=s.span,
            smoothness=s.spec.smoothness,
            extra=-cols * slope[:, None],
        )
        coef = coef + fit.extra
        slope = fit.poly.slope(p.dv - cols @ coef)
        if not terms or np.max(np.abs(fit.extra * np.max(np.abs(cols), axis=0))) < 1e-6 * s.scale:
            break
    resid = p.rate - fit.poly.evaluate(p.dv - cols @ coef)[0]
    return fit.poly, coef, float(np.sum(p.weight * resid**2))


def _mean_sensitivity(p: FitPoints) -> float:
    """Counts per deg/s over the span: the first guess of the model's slope."""
    return float(np.polyfit(p.rate, p.dv, 1)[0]) or 1.0


def fit_structure(blocks: Blocks, s: Structure, duration_s: float) -> Fit:
    """Joint least squares of base model and terms; each time constant (warm-up, channel lag)
    by grid search on these blocks, one after the other."""
    terms = s.terms
    for group in tau_groups(terms):
        terms = with_tau(terms, _best_tau(blocks, replace(s, terms=terms), duration_s, group), group)
    poly, coef, _ = _solve(blocks, s, terms)
    return Fit(poly, tuple(replace(t, coefficient=float(c)) for t, c in zip(terms, coef, strict=True)))


def _best_tau(
    blocks: Blocks, s: Structure, duration_s: float, group: tuple[str, str | None] = ("warmup", None)
) -> float:
    """τ of one group of terms (the warm-up, or one channel's lag), or a gated channel's knee:
    the best of a log grid, refined between its neighbours.

    A τ off by a grid step leaves an exponential-shaped residual that a drift
    term would then "explain" (for a lag: a derivative term); refining removes
    that false second effect.
    """
    warmup = group[0] == "warmup"
    if group[0] == "gated":  # a knee in raw units, searched on the same footing as a lag's τ
        grid = knee_grid(blocks)
    else:
        grid = tau_grid(duration_s) if warmup else lag_grid(duration_s)
    # A lag's τ is searched on the linearised fit (one Gauss-Newton step): its terms
    # are small next to full scale, and there may be one lag per channel to search.
    steps = GAUSS_NEWTON_STEPS if warmup else 1

    def rss(log_tau: float) -> float:
        return _solve(blocks, s, with_tau(s.terms, float(np.exp(log_tau)), group), steps)[2]

    i = int(np.argmin([rss(np.log(t)) for t in grid]))
    lo, hi = np.log(grid[max(i - 1, 0)]), np.log(grid[min(i + 1, grid.size - 1)])
    xatol = 1e-3 if warmup else 1e-2
    res = optimize.minimize_scalar(rss, bounds=(lo, hi), method="bounded", options={"xatol": xatol})
    return float(np.exp(res.x))


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
    """Held-out masks leaving whole plateaus out, interleaved in time; the extreme rates always train."""
    plateaus = np.unique(blocks.plateau)
    rates = np.array([blocks.points.rate[blocks.plateau == p][0] for p in plateaus])
    edge = np.isin(rates, [rates.min(), rates.max()])
    inner = plateaus[~edge]
    k = max(2, min(k, inner.size))
    return [np.isin(blocks.plateau, inner[f::k]) for f in range(k)]


def held_out_errors(blocks: Blocks, s: Structure, folds: list[np.ndarray], duration_s: float) -> np.ndarray:
    errors = np.zeros(len(blocks))
    for held in folds:
        fit = fit_structure(blocks.take(~held), s, duration_s)
        errors[held] = predict(fit, blocks.take(held)) - blocks.points.rate[held]
    return errors


def rms(e: np.ndarray) -> float:
    return float(np.sqrt(np.mean(e**2)))


@dataclass
class Scorer:
    """Held-out rms and training RSS of structures, cached by their terms and size."""

    blocks: Blocks
    folds: list[np.ndarray]
    duration_s: float
    cache: dict[Any, tuple[float, float, int]] = field(default_factory=dict)

    def score(self, s: Structure) -> tuple[float, float, int]:
        """(held-out rms, training RSS of plateau-mean residuals, number of coefficients)."""
        key = (s.spec, tuple(s.knots), s.terms)
        if key not in self.cache:
            err = held_out_errors(self.blocks, s, self.folds, self.duration_s)
            fit = fit_structure(self.blocks, s, self.duration_s)
            resid = self.blocks.points.rate - predict(fit, self.blocks)
            n_par = (len(s.knots) + 1) * (s.spec.order + 1) + len(s.terms)
            self.cache[key] = (rms(err), plateau_rss(self.blocks, resid), n_par)
        return self.cache[key]

    @property
    def n_plateaus(self) -> int:
        return int(np.unique(self.blocks.plateau).size)


def plateau_rss(blocks: Blocks, resid: np.ndarray) -> float:
    """Weighted RSS of per-plateau mean residuals.

    Blocks of one plateau share its table-rate error and slow disturbances, so
    they are not independent; the F-test counts plateaus, not blocks.
    """
    _, idx = np.unique(blocks.plateau, return_inverse=True)
    w = np.bincount(idx, blocks.points.weight)
    mean = np.bincount(idx, blocks.points.weight * resid) / w
    return float(np.sum(w * mean**2))


def f_test(small: tuple[float, float, int], big: tuple[float, float, int], n: int) -> tuple[float, float]:
    """Nested-model F statistic and p-value (RSS from weighted least squares)."""
    k = max(big[2] - small[2], 1)
    dof = max(n - big[2], 1)
    f = ((small[1] - big[1]) / k) / max(big[1] / dof, 1e-300)
    return float(f), float(stats.f.sf(f, k, dof))


def recommend(a: Candidate, b: Candidate) -> str:
    """The session that would tell two confounded explanations apart."""
    kinds = {a.kind, b.kind}
    names = {c.kind: c for c in (a, b)}
    if kinds == {"channel", "time"} and names["channel"].name.startswith(("d/dt", "lag(", "sign")):
        ch = names["channel"].channel
        return (
            f"record a session that cycles {ch} up and down after the sensor is warm (powered on long "
            f"before the first plateau), so that changes of {ch} no longer follow time since power-on"
        )
    if kinds == {"channel", "time"}:
        ch = names["channel"].channel
        return (
            f"record a session in which {ch} does not follow time since power-on: soak the sensor "
            f"before powering it on, then step {ch} up and down in random order"
        )
    if kinds == {"channel"} and a.channel == b.channel:
        return (f"record a session in which {a.channel} changes at several speeds and holds between "
                "changes, so its level, its rate of change and its direction of change separate")
    if kinds == {"channel"}:
        return f"record a session in which {a.channel} and {b.channel} are varied independently"
    if "direction" in kinds:
        return "record a session that approaches each rate from above and below, in random order"
    return "record a longer session with several power cycles, so warm-up and drift separate"


@dataclass
class LoopResult:
    """What the loop found, for the coefficient set, the report and the plots."""

    fit: Fit
    structure: Structure
    blocks: Blocks
    base_fit: Fit
    effects: list[dict[str, Any]]
    confounded: list[dict[str, Any]]
    rounds: list[list[dict[str, Any]]]
    rms_before: float
    rms_after: float
    errors_before: np.ndarray
    errors_after: np.ndarray
    capacity_changes: list[str]
    untestable: dict[str, float] = field(default_factory=dict)
    # Each change to the model in order, with the held-out error after it (same scheme throughout),
    # so a report can be read from the rate model alone down to the set that was written.
    steps: list[dict[str, Any]] = field(default_factory=list)
    candidates: list[Candidate] = field(default_factory=list)  # every candidate built, for the residual


def _step(scorer: Scorer, s: Structure, what: str) -> dict[str, Any]:
    rms_dps, _, _ = scorer.score(s)
    return {"step": what, "spec": s.spec.describe(), "terms": len(s.terms), "held_out_rms_dps": rms_dps}


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


def reselect_size(scorer: Scorer, s: Structure, duration_s: float) -> Structure:
    """Once an effect is in, choose the base size again: the effect may have hidden what it needs."""
    corrected = corrected_points(scorer.blocks, fit_structure(scorer.blocks, s, duration_s))
    try:
        spec, _ = select_model(corrected, s.spec)
    except CanicalError:
        return s
    resized = _with_spec(scorer.blocks, s, spec, duration_s)
    if resized is None or scorer.score(resized)[0] >= scorer.score(s)[0]:
        return s
    return resized


def _with_spec(blocks: Blocks, s: Structure, spec: ModelSpec, duration_s: float) -> Structure | None:
    """Re-choose segment points for a new base size, on blocks corrected by the current terms."""
    corrected = corrected_points(blocks, fit_structure(blocks, s, duration_s))
    try:
        fitted = fit_model(corrected, spec)
    except (CanicalError, np.linalg.LinAlgError):  # a size the data cannot support: no candidate
        return None
    if fitted.spec.n_segments != spec.n_segments:
        return None
    assert isinstance(fitted.model, PiecewisePoly)  # the loop's base is segmented-inverse
    return replace(s, spec=spec, knots=fitted.model.knots)


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
    scorer = Scorer(blocks, folds, duration_s)
    s = Structure(spec, np.asarray(knots, dtype=float), scale, span)
    pool = build_candidates(blocks, duration_s)
    every_candidate = list(pool)
    tied = untestable(pool, blocks)
    if tied:
        progress(f"not testable here (follow the table rate): {', '.join(tied)}")
    pool = [c for c in pool if c.name not in tied]
    n_candidates = len(pool) + 2
    alpha = ALPHA / max(n_candidates, 1)
    min_gain = max(MIN_GAIN, 2.0 / np.sqrt(2.0 * scorer.n_plateaus))
    base_score = scorer.score(s)
    effects: list[dict[str, Any]] = []
    confounded: list[dict[str, Any]] = []
    rounds: list[list[dict[str, Any]]] = []
    capacity_changes: list[str] = []
    steps = [_step(scorer, s, "rate model alone")]
    for _round in range(12):
        current = scorer.score(s)
        progress(f"round {len(rounds) + 1}: held-out rms {current[0]:.4f} deg/s, {len(pool)} candidates")
        table: list[dict[str, Any]] = []
        passing: list[tuple[float, str, Any]] = []
        for cand in pool:
            sc = scorer.score(replace(s, terms=s.terms + cand.terms))
            f, p = f_test(current, sc, scorer.n_plateaus)
            ok = sc[0] < current[0] * (1 - min_gain) and p < alpha
            table.append(
                {"candidate": cand.name, "held_out_rms_dps": sc[0], "f": f, "p": p, "passes": bool(ok)}
            )
            if ok:
                passing.append((sc[0], cand.name, cand))
        for cap in _capacity_options(s):
            bigger = _with_spec(blocks, s, cap, duration_s)
            if bigger is None:
                continue
            sc = scorer.score(bigger)
            f, p = f_test(current, sc, scorer.n_plateaus)
            ok = sc[0] < current[0] * (1 - min_gain) and p < alpha
            name = f"capacity:{cap.describe()}"
            table.append({"candidate": name, "held_out_rms_dps": sc[0], "f": f, "p": p, "passes": bool(ok)})
            if ok:
                passing.append((sc[0], name, bigger))
        rounds.append(table)
        if not passing:
            break
        passing.sort(key=lambda x: x[0])
        _, best_name, best = passing[0]
        if isinstance(best, Structure):
            capacity_changes.append(best_name)
            s = best
            steps.append(_step(scorer, s, f"base model grown to {s.spec.describe()}"))
            continue
        # Every candidate, not only those that passed at the current base size: with its
        # own best base size a candidate may turn out to explain the same residual.
        best, twins, shadows = _confounded_with(scorer, s, best, pool, min_gain)
        if twins:
            chosen = next((c for c in (best, *twins) if c.name in prefer), None)
            group = [best, *twins]
            confounded.append(
                {
                    "candidates": [c.name for c in group],
                    "weaker_alternatives": [c.name for c in shadows],
                    "held_out_rms_dps": {
                        c.name: scorer.score(replace(s, terms=s.terms + c.terms))[0] for c in group
                    },
                    "held_out_rms_before_dps": current[0],
                    "resolved_by_user": chosen.name if chosen else None,
                    "recommendation": recommend(best, twins[0]),
                }
            )
            # Shadows explain a part of the same residual: accepting one later would be a guess too.
            pool = [c for c in pool if c not in group and c not in shadows]
            if chosen is None:
                continue
            best = chosen
        pruned = _prune(scorer, s, best)
        s_new = replace(s, terms=s.terms + pruned.terms)
        after = scorer.score(s_new)
        f, p = f_test(current, after, scorer.n_plateaus)
        fit_now = fit_structure(blocks, s_new, duration_s)
        effects.append(
            {
                "kind": best.kind,
                "channel": best.channel,
                "name": best.name,
                "evidence": {
                    "test": "leave-plateaus-out cross-validation and nested F-test",
                    "held_out_gain": 1.0 - after[0] / current[0],
                    "min_gain": min_gain,
                    "f_statistic": f,
                    "p_value": p,
                    "alpha": alpha,
                },
                "terms": [t.to_dict() for t in fit_now.terms[len(s.terms) :]],
                "rms_before_dps": current[0],
                "rms_after_dps": after[0],
            }
        )
        progress(f"accepted {best.name}: held-out rms {current[0]:.4f} -> {after[0]:.4f} deg/s")
        steps.append(_step(scorer, s_new, f"added {best.name}"))
        s = reselect_size(scorer, s_new, duration_s)
        if s is not s_new:
            steps.append(_step(scorer, s, "base size chosen again with the effect in"))
        pool = [c for c in pool if c is not best]
    pruned_all = _prune_all(scorer, s)
    if len(pruned_all.terms) != len(s.terms):
        steps.append(_step(scorer, pruned_all, "terms that no longer pay removed"))
    s = pruned_all
    final_fit = fit_structure(blocks, s, duration_s)
    # Effect terms in the report carry the final joint coefficients of the terms that stayed.
    final_terms = {(t.kind, t.channel, t.feature, t.form, t.reference): t for t in final_fit.terms}
    for eff in effects:  # a readable name with the final time constant: lag(temp_c, τ=140 s)
        lagged = [t for t in final_fit.terms if t.channel == eff["channel"] and t.feature == "lag"]
        gated = [t for t in final_fit.terms if t.channel == eff["channel"] and t.feature == "gated"]
        is_lag = lagged and eff["name"].startswith("lag(")
        eff["description"] = lagged[0].describe() if is_lag else eff["name"]
        if gated and eff["name"] == gated_name(eff["channel"]):  # temp_c × (|rate| > 30 dps)
            eff["description"] = gated_name(eff["channel"], knee_dps(final_fit.poly, gated[0].threshold_raw))
    for eff in effects:
        keys = [(t["kind"], t["channel"], t["feature"], t["form"], t["reference"]) for t in eff["terms"]]
        eff["terms"] = [final_terms[k].to_dict() for k in keys if k in final_terms]
    effects = [e for e in effects if e["terms"]]
    base_s = Structure(spec, np.asarray(knots, dtype=float), scale, span)
    return LoopResult(
        fit=final_fit,
        structure=s,
        blocks=blocks,
        base_fit=fit_structure(blocks, base_s, duration_s),
        effects=effects,
        confounded=confounded,
        rounds=rounds,
        rms_before=base_score[0],
        rms_after=scorer.score(s)[0],
        errors_before=held_out_errors(blocks, base_s, folds, duration_s),
        errors_after=held_out_errors(blocks, s, folds, duration_s),
        capacity_changes=capacity_changes,
        untestable=tied,
        steps=steps,
        candidates=every_candidate,
    )


def _confounded_with(
    scorer: Scorer, s: Structure, best: Candidate, pool: list[Candidate], min_gain: float
) -> tuple[Candidate, list[Candidate], list[Candidate]]:
    """The best explanation and the candidates that explain the same residual: (best, twins, shadows).

    Each explanation is scored with the base size it deserves (an under-sized base
    leaves misfit that would blur the comparison), and the best is chosen again on
    that footing. Another candidate explains the same residual when adding it on
    top of the best gains less than ``min_gain``. It is a *twin* when, on its own,
    it is as good as the best within ``min_gain`` and the best adds no such gain on
    top of it either — the data cannot tell them apart — and a *shadow* otherwise.
    """

    def grown_rms(terms: tuple[Term, ...]) -> float:
        grown = reselect_size(scorer, replace(s, terms=s.terms + terms), scorer.duration_s)
        return scorer.score(grown)[0]

    r_now = scorer.score(s)[0]
    # A candidate that gains nothing at the current size is not re-scored with its own
    # size (that costs a model selection each); one that gains a little might still tie.
    hopeful = [c for c in pool if c is best
               or scorer.score(replace(s, terms=s.terms + c.terms))[0] < r_now * (1 - min_gain / 2)]
    alone = {c.name: grown_rms(c.terms) for c in hopeful}
    useful = [c for c in hopeful if alone[c.name] < r_now * (1 - min_gain)] or [best]
    best = min(useful, key=lambda c: alone.get(c.name, r_now))
    r_best = alone.get(best.name, r_now)
    twins: list[Candidate] = []
    shadows: list[Candidate] = []
    for other in useful:
        if other is best:
            continue
        r_other = alone[other.name]
        r_both = grown_rms(best.terms + other.terms)
        if r_both >= r_best * (1 - min_gain):
            is_twin = r_other <= r_best * (1 + min_gain) and r_both >= r_other * (1 - min_gain)
            (twins if is_twin else shadows).append(other)
    # A channel's level is its lag with τ → 0: when the two tie, the data do not need
    # the lag's time constant, and the simpler one is the answer (not a confound).
    level = next((c for c in twins if _nests(best, c)), None)
    if level is not None:
        twins.remove(level)
        shadows.append(best)
        best = level
    for twin in [c for c in twins if _nests(c, best)]:
        twins.remove(twin)
        shadows.append(twin)
    return best, twins, shadows


def _nests(general: Candidate, simple: Candidate) -> bool:
    """True when ``simple`` is ``general`` in a limit (a channel's level is its lag at τ → 0,
    and its rate-gated form at knee → 0)."""
    generalises = general.name.startswith("lag(") or general.name == gated_name(general.channel or "")
    return (general.kind == simple.kind == "channel" and general.channel == simple.channel
            and generalises and simple.name.startswith("channel:"))


def knee_dps(poly: PiecewisePoly, knee_raw: float | None) -> float:
    """A knee in raw units as a rate: the mean |ω| the model gives at ΔV = ±knee."""
    k = float(knee_raw or 0.0)
    w = poly.evaluate(np.array([-k, k]))[0]
    return float(np.mean(np.abs(w)))


def _prune_all(scorer: Scorer, s: Structure) -> Structure:
    """With the final base size, drop any accepted column that no longer earns its keep."""
    terms = s.terms
    while len(terms) > 1:
        full = scorer.score(replace(s, terms=terms))[0]
        trials = [
            (scorer.score(replace(s, terms=terms[:i] + terms[i + 1 :]))[0], i) for i in range(len(terms))
        ]
        best_rms, i = min(trials)
        if best_rms > full * (1 + PRUNE_TOLERANCE):
            break
        terms = terms[:i] + terms[i + 1 :]
    return replace(s, terms=terms)


def _prune(scorer: Scorer, s: Structure, cand: Candidate) -> Candidate:
    """Drop the candidate's columns one at a time while held-out error does not suffer."""
    terms = cand.terms
    changed = True
    while changed and len(terms) > 1:
        changed = False
        full = scorer.score(replace(s, terms=s.terms + terms))[0]
        trials = []
        for i in range(len(terms)):
            fewer = terms[:i] + terms[i + 1 :]
            trials.append((scorer.score(replace(s, terms=s.terms + fewer))[0], fewer))
        best_rms, fewer = min(trials, key=lambda x: x[0])
        if best_rms <= full * (1 + PRUNE_TOLERANCE):
            terms = fewer
            changed = True
    return cand.with_terms(terms)
