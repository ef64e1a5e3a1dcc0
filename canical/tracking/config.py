"""What a bias tracker is told: noise figures, window, bounds, slew and the cue.

Why one frozen record: the daemon's YAML, the offline command and the tests all build the
same settings, and the tracker reads nothing else, so the same settings give the same output.
"""

from __future__ import annotations

import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, replace
from typing import Any

SQRT_HOUR = 60.0  # √(3600 s): deg/√h → deg/s/√Hz
#: A field-measured slope leaves at most this many of its standard errors: the tracker's prior.
FIELD_SLOPE_SES = 3.0


@dataclass(frozen=True)
class TrackerConfig:
    """Settings of a bias tracker (all rates in deg/s, temperatures in °C, times in s)."""

    arw_deg_rt_h: float = 0.5  # the set's angle random walk: white rate noise N in deg/√h
    window_s: float = 1.0  # statistics are taken, and decisions made, once per window
    k_std: float = 3.0  # a still window's sample spread is within k_std x the white noise ...
    vibration_dps: float = 0.3  # ... plus this much (engine idle vibration, rms)
    k_steady: float = 4.0  # a window's mean agrees with the run's last few within k_steady x σ
    steady_windows: int = 5  # ... the last this many windows of the run
    min_run_windows: int = 3  # a standstill is learned from once it has this many still windows
    k_gate: float = 5.0  # ... if its mean agrees with the learned bias within k_gate x σ,
    trust_run_windows: int = 6  # ... or once it has this many (long enough to overrule it)
    bound_dps: float = 1.0  # plausibility: a bias beyond this is refused (a turn, not a bias)
    slew_dps_per_s: float = 0.05  # the applied bias moves at most this fast: no step in the output
    turn_on_sigma_dps: float = 0.5  # turn-on repeatability: prior spread of a new power-on's bias
    temp_slope_sigma: float = 0.02  # prior spread of the bias's temperature slope, deg/s/°C
    bias_walk_dps_rt_s: float = 2e-4  # how fast the bias wanders between stops, (deg/s)/√s
    window_inflation: float = 2.0  # a window's mean is not independent of its neighbours'
    reference_c: float = 25.0  # temperature at which the learned offset is stated
    cue_threshold: float | None = None  # a cue within ± this: stopped (reverse moves); None: no cue

    def __post_init__(self) -> None:
        for name in ("arw_deg_rt_h", "window_s", "k_std", "k_steady", "bound_dps", "slew_dps_per_s",
                     "turn_on_sigma_dps", "temp_slope_sigma", "window_inflation"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive number, not {value!r}")
        for name in ("steady_windows", "min_run_windows", "trust_run_windows"):
            value = getattr(self, name)
            if not (isinstance(value, int) and value >= 1):
                raise ValueError(f"{name} must be a whole number of at least 1, not {value!r}")
        if self.k_gate <= 0 or not math.isfinite(self.k_gate):
            raise ValueError(f"k_gate must be a positive number, not {self.k_gate!r}")
        for name in ("vibration_dps", "bias_walk_dps_rt_s"):
            value = getattr(self, name)
            if not (math.isfinite(value) and value >= 0):
                raise ValueError(f"{name} must be a non-negative number, not {value!r}")
        if not math.isfinite(self.reference_c):
            raise ValueError("reference_c must be a finite number")
        cue = self.cue_threshold
        if cue is not None and not (math.isfinite(cue) and cue > 0):
            raise ValueError(f"cue_threshold must be a positive number, not {self.cue_threshold!r}")

    def for_set(self, fit: Mapping[str, Any], *, arw_given: bool) -> TrackerConfig:
        """These settings for one axis's set: its angle random walk (``fit.arw_deg_rt_h``, what
        calibrate measured) unless the user gave one; a set without it keeps the default. A set
        whose slope the fleet measured gets the slope prior :meth:`with_field_slope` gives."""
        return self._with_arw(fit, arw_given).with_field_slope([fit])

    def for_sets(self, fits: Sequence[Mapping[str, Any]], *, arw_given: bool) -> TrackerConfig:
        """These settings for one tracker over several axes' sets (an IMU set: a standstill is
        the vehicle's): the noisiest axis's angle random walk tells a standstill."""
        return self._with_arw(max(fits, key=_arw), arw_given).with_field_slope(fits)

    def _with_arw(self, fit: Mapping[str, Any], arw_given: bool) -> TrackerConfig:
        arw = fit.get("arw_deg_rt_h")
        if arw_given or not isinstance(arw, int | float) or not (math.isfinite(arw) and arw > 0):
            return self
        return replace(self, arw_deg_rt_h=float(arw))

    def with_field_slope(self, fits: Sequence[Mapping[str, Any]]) -> TrackerConfig:
        """The slope prior for sets whose temperature slope the fleet measured.

        Why: ``fleet analyse --propose-sets`` writes a set whose temperature term is the field
        slope, known to its standard error (``fit.field_evidence.slope_se``); what it leaves is
        within :data:`FIELD_SLOPE_SES` of those, not the table's ``temp_slope_sigma``. With the
        wide prior the tracker learns a slope from one standstill's few degrees and extrapolates
        it to the next (the error ``fleet replay`` measured after a proposed set). Every axis must
        carry evidence (else the default stays); the widest axis's prior is taken.
        """
        ses = [_field_slope_se(fit) for fit in fits]
        if not ses or any(se is None for se in ses):
            return self
        return replace(self, temp_slope_sigma=FIELD_SLOPE_SES * max(se for se in ses if se is not None))

    @property
    def white_dps_rt_hz(self) -> float:
        """N in deg/s/√Hz: a τ-average of white noise has σ = N/√τ."""
        return self.arw_deg_rt_h / SQRT_HOUR


def _arw(fit: Mapping[str, Any]) -> float:
    value = fit.get("arw_deg_rt_h")
    return float(value) if isinstance(value, int | float) and math.isfinite(value) else 0.0


def _field_slope_se(fit: Mapping[str, Any]) -> float | None:
    """The field slope's standard error a set's ``fit.field_evidence`` gives; None without one."""
    evidence = fit.get("field_evidence")
    se = evidence.get("slope_se") if isinstance(evidence, Mapping) else None
    if not isinstance(se, int | float) or isinstance(se, bool) or not (math.isfinite(se) and se > 0):
        return None
    return float(se)
