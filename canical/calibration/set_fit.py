"""The ``fit`` section a coefficient set carries about its own fit, as a record.

Why a record: the pipeline gathers these figures from the report, and a set written without its
report still says how good it is and, when the closed loop had to choose between explanations it
could not tell apart, that its attribution is a choice. Built once by :func:`set_fit`, turned into
the file's mapping (same keys, same order as the file has always had) only by
:meth:`SetFit.to_dict` where the set is made.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from canical.calibrate.allan import NoiseAnalysis
from canical.calibration.calibration_report import CalibrationReport


@dataclass(frozen=True)
class Ambiguity:
    """One confounded group as the set records it: the explanation adopted, those the session could
    not tell from it, why that one, and the session that would separate them."""

    adopted: str
    alternatives: tuple[str, ...]
    rule: str
    separate_by: str

    def to_dict(self) -> dict[str, Any]:
        return {"adopted": self.adopted, "alternatives": list(self.alternatives), "rule": self.rule,
                "separate_by": self.separate_by}


@dataclass(frozen=True)
class LoopFit:
    """What the closed loop adds to the section: the written set's held-out figures, the rate
    model's kept beside them, the effects, the ambiguities, what is left unexplained."""

    held_out_rms_dps: float
    held_out_max_dps: float
    method: str
    effects: tuple[str, ...]
    ambiguous: tuple[Ambiguity, ...]
    unexplained_ratio: float | None


@dataclass(frozen=True)
class SetFit:
    """The figures a set carries about its own fit; ``loop`` None when the closed loop did not run."""

    samples_used: int
    plateaus: int
    training_rms_dps: float
    training_max_dps: float
    held_out_rms_dps: float  # the rate model's, leave-rates-out
    held_out_max_dps: float
    arw_deg_rt_h: float | None
    loop: LoopFit | None

    def to_dict(self) -> dict[str, Any]:
        """The file's ``fit`` mapping: with the loop, its headline is the written set's, effects and all."""
        out: dict[str, Any] = {"samples_used": self.samples_used, "plateaus": self.plateaus,
                               "training_rms_dps": self.training_rms_dps,
                               "training_max_dps": self.training_max_dps}
        loop = self.loop
        if loop is None:
            out |= {"held_out_rms_dps": self.held_out_rms_dps, "held_out_max_dps": self.held_out_max_dps}
        else:
            out |= {"held_out_rms_dps": loop.held_out_rms_dps, "held_out_max_dps": loop.held_out_max_dps,
                    "held_out_method": loop.method,
                    "rate_model_held_out_rms_dps": self.held_out_rms_dps,
                    "rate_model_held_out_max_dps": self.held_out_max_dps}
        if self.arw_deg_rt_h is not None:
            out["arw_deg_rt_h"] = self.arw_deg_rt_h
        if loop is not None:
            out |= {"extended_held_out_rms_dps": loop.held_out_rms_dps, "effects": list(loop.effects)}
            if loop.ambiguous:
                out["ambiguous"] = [a.to_dict() for a in loop.ambiguous]
            if loop.unexplained_ratio is not None:
                out["unexplained_ratio"] = loop.unexplained_ratio
        return out


def set_arw(report: CalibrationReport) -> float | None:
    """The angle random walk the set carries (deg/√h), for telling a standstill on the vehicle.

    From the Allan analysis of the zero-rate plateaus when it resolved the term; else from the
    plateaus' per-sample noise at the session's sample rate (white noise: N = σ·√Δt). None when
    the session shows neither.
    """
    allan = report.allan
    if not isinstance(allan, NoiseAnalysis):
        return None
    if allan.terms.arw.resolved:
        return float(allan.terms.arw.value)
    rate_hz = allan.curve.sample_rate_hz * (allan.samples_per_point or 1)
    sigma = report.noise.per_sample_dps
    if rate_hz and np.isfinite(sigma) and sigma > 0:
        return float(sigma / np.sqrt(rate_hz) * 60.0)
    return None


def ambiguities(report: CalibrationReport) -> tuple[Ambiguity, ...]:
    """Each confounded group whose explanation was adopted: the set then says itself that its
    attribution is a choice, wherever it is read without its report."""
    return tuple(Ambiguity(c.adopted, tuple(n for n in c.candidates if n != c.adopted), c.adoption_rule,
                           c.recommendation)
                 for c in report.confounded if c.adopted)


def set_fit(report: CalibrationReport) -> SetFit:
    """The set's ``fit`` section from the report."""
    loop = None
    if report.closed_loop is not None:
        ratio = report.unexplained.ratio if report.unexplained is not None else None
        loop = LoopFit(report.closed_loop.held_out_rms_after_dps, report.closed_loop.held_out_max_after_dps,
                       report.closed_loop.method, tuple(e.name for e in report.effects), ambiguities(report),
                       ratio if ratio is not None and np.isfinite(ratio) else None)
    return SetFit(report.samples.used, report.plateaus, report.training.rms_dps, report.training.max_dps,
                  report.held_out.rms_dps, report.held_out.max_dps, set_arw(report), loop)
