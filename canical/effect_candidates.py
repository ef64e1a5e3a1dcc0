"""Candidate explanations of a residual, built from the session itself.

Every auxiliary column is a candidate by its name (its meaning is never
assumed), and so are time since power-on (a warm-up 1 − exp(−t/τ) with τ
estimated, and a linear drift) and the direction of approach (the raw signal's
last significant change, up or down) and its rate of change. Each candidate brings its terms in bias
form (ΔV gains c·x) and scale-factor form (ΔV gains c·x·ΔV); a channel also brings a
quadratic bias. Columns that do not earn their keep are pruned after acceptance.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from canical.blocks import SLOPE_TAU_S, Blocks
from canical.terms import TIME_INPUT, Term

TAU_GRID_POINTS = 24


@dataclass(frozen=True)
class Candidate:
    """A named group of term templates (coefficients still to be fitted)."""

    name: str
    kind: str  # channel | time | direction
    channel: str | None
    terms: tuple[Term, ...]

    def describe(self) -> str:
        return self.name

    def with_terms(self, terms: tuple[Term, ...]) -> Candidate:
        return replace(self, terms=terms)


def feature(term: Term, blocks: Blocks) -> np.ndarray:
    """The term's feature x at each block (block means of the run-time inputs)."""
    if term.feature == "sign":
        return blocks.direction
    if term.feature == "slope":
        return blocks.slope
    if term.kind == "time":
        t = blocks.time_s
        return 1.0 - np.exp(-t / term.tau_s) if term.feature == "warmup" else t
    x = blocks.aux[term.channel] - term.reference
    return x * x if term.feature == "square" else x


def shift_columns(terms: tuple[Term, ...], blocks: Blocks) -> np.ndarray:
    """Per term, what one unit of its coefficient adds to ΔV at each block: x, or x·ΔV."""
    if not terms:
        return np.zeros((len(blocks), 0))
    dv = blocks.points.dv
    return np.column_stack([feature(t, blocks) * (dv if t.form == "scale" else 1.0) for t in terms])


def _pair(kind: str, feature_name: str, **kw) -> tuple[Term, ...]:
    return tuple(
        Term(kind=kind, feature=feature_name, form=form, coefficient=0.0, **kw) for form in ("bias", "scale")
    )


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
            *_pair("channel", "offset", channel=name, reference=ref),
            Term(kind="channel", feature="square", form="bias", coefficient=0.0, channel=name, reference=ref),
        )
        out.append(Candidate(f"channel:{name}", "channel", name, terms))
    if np.ptp(blocks.time_s) > 0:
        tau = float(session_duration_s) / 3.0
        out.append(Candidate("time:warm-up", "time", None, _pair("time", "warmup", tau_s=tau)))
        out.append(Candidate("time:linear-drift", "time", None, _pair("time", "linear")))
    if np.ptp(blocks.direction) > 0:
        out.append(
            Candidate(
                "direction",
                "direction",
                None,
                _pair("direction", "sign", threshold_raw=blocks.direction_threshold_raw),
            )
        )
    # On settled plateaus the rate of change is near zero; it is a candidate all the same,
    # so that a sensor still moving in its plateaus would show it.
    if np.ptp(blocks.slope) > 0:
        out.append(
            Candidate("rate-of-change", "direction", None, _pair("direction", "slope", tau_s=SLOPE_TAU_S))
        )
    return out


def tau_grid(session_duration_s: float) -> np.ndarray:
    """Warm-up time constants worth trying: from seconds to beyond the session's length."""
    return np.geomspace(5.0, max(10.0, 3.0 * session_duration_s), TAU_GRID_POINTS)


def with_tau(terms: tuple[Term, ...], tau: float) -> tuple[Term, ...]:
    return tuple(replace(t, tau_s=tau) if t.feature == "warmup" else t for t in terms)


def uses_time(terms: tuple[Term, ...]) -> bool:
    return any(t.input_name == TIME_INPUT for t in terms)
