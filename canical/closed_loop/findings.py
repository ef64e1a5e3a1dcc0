"""What the closed loop found, as named records: scores, round tables, steps, effects, confounds.

The loop, the report, the plots and the evaluation read these by field name, not by
position or string key. ``to_dict`` gives the report's JSON form; the field order of each
record is the key order of its JSON object, so the report file stays as it was.
No numpy here: the report's Markdown and the CLI's summary read these records cheaply.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, field, replace
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from canical.closed_loop.candidates import Candidate
    from canical.sets.terms import Term

EVIDENCE_TEST = "leave-plateaus-out cross-validation and nested F-test"


@dataclass(frozen=True)
class Score:
    """How well one structure does: the loop ranks by the first, the F-test reads all three."""

    held_out_rms_dps: float
    training_rss: float  # weighted RSS of plateau-mean residuals (the F-test counts plateaus)
    n_par: int  # coefficients of base model and terms


@dataclass(frozen=True)
class RoundRow:
    """One candidate (or a bigger base) in one round: its score against the current model."""

    candidate: str
    held_out_rms_dps: float
    f: float
    p: float
    passes: bool


@dataclass(frozen=True)
class LoopStep:
    """One change to the model, with the held-out error after it (one scheme throughout)."""

    step: str
    spec: str
    terms: int
    held_out_rms_dps: float


@dataclass(frozen=True)
class Evidence:
    """Why an effect was accepted: the held-out gain and the nested F-test, with their bars."""

    held_out_gain: float
    min_gain: float
    f_statistic: float
    p_value: float
    alpha: float
    test: str = EVIDENCE_TEST

    def to_dict(self) -> dict[str, Any]:
        return {"test": self.test, **{k: v for k, v in asdict(self).items() if k != "test"}}


@dataclass(frozen=True)
class Effect:
    """An accepted effect: its candidate, the evidence, and its terms with final coefficients."""

    kind: str
    channel: str | None
    name: str
    evidence: Evidence
    terms: tuple[Term, ...]  # with their final coefficients; the file's form only in to_dict
    rms_before_dps: float
    rms_after_dps: float
    description: str = ""  # a readable name with the final time constant or knee; "" until known
    # The twins the data could not tell this effect from, when it was adopted among them (by the
    # loop's rule or the user's --prefer): the attribution is ambiguous, the correction is not.
    ambiguous_with: tuple[str, ...] = ()

    @property
    def label(self) -> str:
        """The description when there is one, else the candidate's name."""
        return self.description or self.name

    def to_dict(self) -> dict[str, Any]:
        terms = [t.to_dict() for t in self.terms]
        return {**asdict(self), "evidence": self.evidence.to_dict(), "terms": terms}


@dataclass(frozen=True)
class Confound:
    """Candidates that explain the same residual; one of them is adopted (the user's, or the
    loop's rule's: see ``search.ADOPTION_RULE``) and the attribution marked ambiguous."""

    candidates: tuple[str, ...]
    weaker_alternatives: tuple[str, ...]
    held_out_rms_dps: dict[str, float]  # each with the base size it deserves, as compared
    paired_p: dict[str, float]  # one-sided paired p that the first predicts better than each twin
    paired_alpha: float
    held_out_rms_before_dps: float
    resolved_by_user: str | None
    recommendation: str  # the session that would separate them
    adopted: str | None = None  # the twin whose terms went into the set
    adoption_rule: str = ""  # why that one: the user's --prefer, or the loop's rule
    # A channel's form that did not beat an equally flexible drift of the session's own clock: no
    # term of either goes into the set ("drift, confounded with <channel>").
    drift_of_session: bool = False
    # With drift_of_session: the share of the error of stretches of the session it was not fitted
    # on that the channel's form removed (a real effect removes most of it).
    stretch_gain: float | None = None
    # With drift_of_session: the share of the held-out error the drift leaves that the channel's
    # form removed on top of it (a real effect of a drifting sensor removes much of it).
    beyond_drift_gain: float | None = None
    # With drift_of_session, where that share was large: the share of what a drift of a stretch of
    # the session leaves that the form, fitted with the drift on the other stretches, removes there
    # (a real effect carries into a stretch it did not see; a fit to this session's wander does not).
    beyond_drift_stretch_gain: float | None = None

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class Comparison:
    """One candidate next to the best explanation, both on the base size they deserve."""

    held_out_rms_dps: float
    p_best_better: float


@dataclass
class ConfoundCheck:
    """The best explanation and those that explain the same residual, as the check sorts them
    (see ``search._confounded_with``); a working record, so not frozen."""

    best: Candidate
    twins: list[Candidate] = field(default_factory=list)
    shadows: list[Candidate] = field(default_factory=list)
    evidence: dict[str, Comparison] = field(default_factory=dict)

    def with_p(self, name: str, p: float) -> None:
        """Record a new paired p for ``name``, judged against a new best."""
        self.evidence[name] = replace(self.evidence[name], p_best_better=p)
