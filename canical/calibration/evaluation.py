"""Judge calibrations on data they were not fitted to: the paper's comparisons.

* :func:`compare_models` — each model fitted on a training session, judged on the
  plateau means of a second session at other rates (the paper's Fig. 2 question);
* :func:`validation_record` — the paper's Fig. 3 test: a long record at one rate,
  smoothed by a sliding mean, corrected sample by sample.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from canical.calibrate.cross_validation import prediction_errors
from canical.calibrate.fit_points import FitPoints, fit_points
from canical.calibrate.plateaus import detect_plateaus, plateau_means
from canical.calibration.pipeline import CalibrateOptions, CalibrationResult, calibrate, fit_base
from canical.closed_loop.candidates import Candidate
from canical.closed_loop.search import Scorer, Structure, drift_competitor, plateau_folds, reselect_size
from canical.models.kinds import FORWARD_POLY, SEGMENTED_LINEAR
from canical.models.piecewise import PiecewisePoly
from canical.sessions.session import Session
from canical.sets.coefficients import CoefficientSet
from canical.sets.corrector import Corrector
from canical.sets.term_kinds import CHANNEL, CHANNEL_GATED, DIRECTION_SIGN, TIME_INPUT
from canical.sets.terms import Term

# The models the paper discusses, and ours: (label, options).
PAPER_MODELS: tuple[tuple[str, CalibrateOptions], ...] = (
    (f"{FORWARD_POLY} (eq. 5, order 3)", CalibrateOptions(model=FORWARD_POLY.name, order=3)),
    (f"{SEGMENTED_LINEAR} (eq. 6, 0, ±10 deg/s)", CalibrateOptions(model=SEGMENTED_LINEAR.name)),
    (
        "segmented-inverse (eq. 11, 4 seg, quadratic)",
        CalibrateOptions(segments=4, order=2, smoothness=None),
    ),
    ("segmented-inverse, C0 joins, auto size", CalibrateOptions()),
)


@dataclass(frozen=True)
class ModelScore:
    label: str
    spec: str
    train_rms_dps: float
    test_rms_dps: float
    test_max_dps: float
    model: object
    v0: float


def held_out_points(session: Session, v0: float) -> FitPoints:
    """Plateau means of an evaluation session, with the training session's V0."""
    plateaus = detect_plateaus(session.time_s, session.reference("score held-out plateaus"))
    return fit_points(session.raw, v0, plateaus)


def compare_models(train: Session, test: Session, models=PAPER_MODELS) -> list[ModelScore]:
    """Fit each model on ``train``, score it on the plateaus of ``test``."""
    scores = []
    for label, options in models:
        base = fit_base(train, options)
        test_points = held_out_points(test, base.v0)
        e_train = prediction_errors(base.fitted.model, base.points)
        e_test = prediction_errors(base.fitted.model, test_points)
        scores.append(
            ModelScore(
                label,
                base.fitted.spec.describe(),
                float(np.sqrt(np.mean(e_train**2))),
                float(np.sqrt(np.mean(e_test**2))),
                float(np.max(np.abs(e_test))),
                base.fitted.model,
                base.v0,
            )
        )
    return scores


def held_out_set_errors(cset: CoefficientSet, session: Session) -> np.ndarray:
    """A written coefficient set judged as :func:`compare_models` judges a model: on plateau means.

    Raw values, time and auxiliary channels are averaged per plateau and corrected as samples, so
    a set without effect terms scores exactly what its model scored in the comparison.
    """
    plateaus = detect_plateaus(session.time_s, session.reference("score held-out plateaus"))
    raw = plateau_means(session.raw, plateaus)
    inputs = {name: plateau_means(values, plateaus) for name, values in session.aux.items()}
    inputs[TIME_INPUT] = plateau_means(session.time_s, plateaus)
    rate, _ = Corrector(cset).correct(raw, inputs)
    return rate - plateaus.rate_dps


def sliding_mean(values: np.ndarray, window: int) -> np.ndarray:
    """Mean over a sliding window (fully covered positions only)."""
    kernel = np.full(window, 1.0 / window)
    return np.convolve(values, kernel, mode="valid")


@dataclass(frozen=True)
class ValidationResult:
    rate_dps: float
    mean_error_dps: float
    std_dps: float


def validation_record(model, v0: float, record: Session, window: int = 100) -> ValidationResult:
    """Smooth the raw record, correct every sample, and compare with the table rate."""
    smoothed = sliding_mean(record.raw, window)
    rate, _ = model.evaluate(smoothed - v0)
    true = float(np.median(record.reference("validate")))
    return ValidationResult(true, float(np.mean(rate) - true), float(np.std(rate)))


@dataclass(frozen=True)
class EffectScore:
    """How the closed loop did on one scenario, all errors on held-out plateaus (deg/s rms)."""

    scenario: str
    found: tuple[str, ...]
    confounded: tuple[tuple[str, ...], ...]
    rms_before: float
    rms_after: float
    rms_oracle: float
    correct: bool
    unexplained_ratio: float = 0.0  # held-out rms after the loop / the session's noise floor
    unexplained: bool = False
    # Per reported confound: the paired test's p that its first candidate predicts better than each twin.
    paired_p: tuple[dict[str, float], ...] = ()
    # The channels of the terms written to the set (an ambiguous adoption's too): what is blamed.
    written_channels: tuple[str, ...] = ()
    # Held-out rms of a model given, instead of the told form, the drift of the session the loop
    # sets against that form (nan where the truth has no channel term). Where the told form does
    # not beat it, the session cannot tell the effect from a drift: no rule can blame the channel
    # there without blaming drifts on channels too.
    rms_drift_told: float = float("nan")
    # Every effect the set carries, an ambiguous adoption's too (``found`` holds the attributed).
    adopted: tuple[str, ...] = ()

    @property
    def drift_separable(self) -> bool:
        """Whether a model told the true form predicts held-out plateaus better than the drift."""
        return bool(self.rms_oracle < self.rms_drift_told)


def score_scenario(scenario, seed: int = 0, dwell_s: float = 10.0, table=None) -> EffectScore:
    """Calibrate a scenario's session with the loop and compare with a model told the effect.

    ``table`` (a :class:`canical.sim.table_recording.TableBehaviour`) records the session as a
    real table would; by default the table ramps at 100 deg/s² with the commanded rate.
    """
    session = scenario.session(seed, dwell_s, table=table)
    result = calibrate(session, CalibrateOptions(), sensor_id="SIM", axis="z")
    loop = result.loop
    model = result.base.fitted.model
    # Default options fit a segmented-inverse model and close the loop on it.
    assert loop is not None and isinstance(model, PiecewisePoly)
    # An effect adopted among confounded twins is the group's correction, not an attribution.
    found = tuple(e.name for e in loop.effects if not e.ambiguous_with)
    # Weaker alternatives (explain part of the same residual) are listed after the twins, marked ~.
    # A channel's form that lost to the session's drift is not a confound among causes: apart.
    groups = tuple(
        (*c.candidates, *(f"~{w}" for w in c.weaker_alternatives)) for c in loop.confounded
        if not c.drift_of_session
    )
    duration = float(session.time_s[-1] - session.time_s[0])
    scorer = Scorer(loop.blocks, plateau_folds(loop.blocks), duration)
    told = _oracle_terms(scenario, loop.blocks)
    rms_oracle = _told_rms(scorer, result, told)
    drift = (drift_competitor(Candidate("told", CHANNEL, None, told), loop.blocks)
             if any(t.kind == CHANNEL for t in told) else None)
    rms_drift = _told_rms(scorer, result, drift.terms) if drift is not None else float("nan")
    in_groups = {name.lstrip("~") for g in groups for name in g}
    correct = (
        scenario.attributed(found)
        and set(scenario.confounded) <= in_groups
        and (bool(groups) == bool(scenario.confounded))
    )
    left = result.report.unexplained
    assert left is not None  # the loop ran
    written = tuple(sorted({t.channel for t in result.coefficients.terms if t.channel}))
    return EffectScore(scenario.name, found, groups, loop.rms_before, loop.rms_after, rms_oracle, correct,
                       left.ratio, left.unexplained, tuple(c.paired_p for c in loop.confounded), written,
                       rms_drift, tuple(e.name for e in loop.effects))


def _told_rms(scorer: Scorer, result: CalibrationResult, terms: tuple[Term, ...]) -> float:
    """Held-out rms of the rate model with ``terms``: on the base size the loop ended with, or
    on one chosen again for them, whichever predicts better."""
    loop, model = result.loop, result.base.fitted.model
    assert loop is not None and isinstance(model, PiecewisePoly)  # score_scenario's own checks
    same_size = Structure(loop.structure.spec, loop.structure.knots, model.scale, model.span, terms)
    base_size = Structure(result.base.fitted.spec, model.knots, model.scale, model.span, terms)
    return min(scorer.held_rms(same_size), scorer.held_rms(reselect_size(scorer, base_size)))


def _oracle_terms(scenario, blocks):
    """The scenario's true term forms, with references the run time would use."""
    terms = []
    for t in scenario.oracle_terms:
        if t.kind == CHANNEL and t.spec is not CHANNEL_GATED:
            t = replace(t, reference=float(np.mean(blocks.aux[t.channel])))
        # A gated level is told where it vanishes: a wrong reference would leave a hinge of the rate.
        if DIRECTION_SIGN.owns(t):
            t = replace(t, params=replace(t.params, threshold_raw=blocks.direction_threshold_raw))
        terms.append(t)
    return tuple(terms)
