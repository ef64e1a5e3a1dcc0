"""The report of a triad calibration as one record: built by the triad pipeline, read by name.

:meth:`canical.calibration.imu_pipeline.ImuCalibration.report` builds an :class:`ImuReport`;
report.json is its :meth:`~ImuReport.to_dict`, report.md and ``coupling.png``
(:mod:`canical.report.imu_report`) and the command's summary (:mod:`canical.commands.calibrate_imu`)
read its fields. Why: the report was a dict whose keys the pipeline, the page, the figure and the
summary each spelled on their own; a field renamed is now one change mypy follows to every reader.
``to_dict`` gives the keys in the order report.json has always had.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from canical.calibrate.coupling import angle_mrad
from canical.sessions.triad_session import AXES


@dataclass(frozen=True)
class SessionErrors:
    """Held-out plateau errors of one session per axis, deg/s rms, before and after the coupling."""

    session: str
    axis: str  # the table axis (x, -y...) or multi
    plateaus: int
    before_rms_dps: tuple[float, float, float]
    after_rms_dps: tuple[float, float, float]
    after_max_dps: float

    def to_dict(self) -> dict[str, Any]:
        return {"session": self.session, "axis": self.axis, "plateaus": self.plateaus,
                "before_rms_dps": dict(zip(AXES, self.before_rms_dps, strict=True)),
                "after_rms_dps": dict(zip(AXES, self.after_rms_dps, strict=True)),
                "after_max_dps": self.after_max_dps}


@dataclass(frozen=True)
class CouplingTerm:
    """One off-diagonal term of M: how much of ``column``'s rate goes into corrected ``row``."""

    row: str
    column: str
    value: float
    standard_error: float

    @property
    def percent(self) -> float:
        return 100.0 * self.value

    @property
    def mrad(self) -> float:
        return angle_mrad(self.value)

    def to_dict(self) -> dict[str, Any]:
        return {"row": self.row, "column": self.column, "value": self.value,
                "standard_error": self.standard_error, "percent": self.percent, "mrad": self.mrad}


@dataclass(frozen=True)
class AxisModel:
    """One axis's own model in the IMU set: its spec, held-out error and the effects it carries."""

    model: str
    held_out_rms_dps: float
    effects: tuple[str, ...]

    def to_dict(self) -> dict[str, Any]:
        return {"model": self.model, "held_out_rms_dps": self.held_out_rms_dps, "effects": list(self.effects)}


@dataclass(frozen=True)
class ImuReport:
    """Everything a triad calibration tells its user; see the module docstring."""

    sessions: tuple[str, ...]
    coefficients: str  # the IMU set's path
    joint_refits: int
    matrix: np.ndarray  # M, (3, 3)
    standard_errors: np.ndarray  # one per term of M
    coupling_plateaus: int
    held_out: tuple[SessionErrors, ...]
    axes: tuple[AxisModel, AxisModel, AxisModel]  # x, y, z

    @property
    def estimation(self) -> str:
        return ("per-axis models on their own sessions, then u = C w by least squares on the table rates "
                "over all single-axis plateaus, M = inverse(C); then "
                f"{self.joint_refits} joint refit(s) kept (each axis refitted on all sessions' "
                "plateaus with decoupled targets, C refitted)")

    @property
    def off_diagonal(self) -> tuple[CouplingTerm, ...]:
        m, se = self.matrix, self.standard_errors
        return tuple(CouplingTerm(AXES[i], AXES[j], float(m[i, j]), float(se[i, j]))
                     for i in range(3) for j in range(3) if i != j)

    def to_dict(self) -> dict[str, Any]:
        """The report.json form (keys in the order the file has always had)."""
        return {
            "kind": "imu-set",
            "sessions": list(self.sessions),
            "coefficients": self.coefficients,
            "estimation": self.estimation,
            "joint_refits": self.joint_refits,
            "coupling": {"matrix": self.matrix.tolist(), "standard_errors": self.standard_errors.tolist(),
                         "plateaus": self.coupling_plateaus,
                         "off_diagonal": [t.to_dict() for t in self.off_diagonal]},
            "held_out": [e.to_dict() for e in self.held_out],
            "axes": {name: a.to_dict() for name, a in zip(AXES, self.axes, strict=True)},
        }
