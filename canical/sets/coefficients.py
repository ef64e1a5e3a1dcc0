"""The coefficient set: the one artefact that leaves a calibration.

Plain, serialisable data (see :mod:`canical.sets.coefficient_file` for YAML and the
CRC), separate from the code that computes it and from the code that applies it.
The set is typed records, parsed once at load: ``model`` is the record of its kind
(:mod:`canical.sets.set_model`), ``terms`` the validated effect terms the closed loop
added (empty for a plain model), each holding its kind object. Older files that lack
newer optional keys still load and write back as read; a file naming a term kind or a
model key this version does not know is refused.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

from canical.models.forward_poly import ForwardPoly
from canical.models.kinds import ModelKind
from canical.models.piecewise import PiecewisePoly
from canical.sets.set_model import (
    OUT_OF_SPAN_BEHAVIOUR,
    ForwardModel,
    PiecewiseModel,
    SetModel,
    finite,
    forward_model,
    piecewise_model,
)
from canical.sets.terms import Term

__all__ = [
    "DEFAULT_RAW_UNITS", "OUT_OF_SPAN_BEHAVIOUR", "SCHEMA_VERSION", "CoefficientSet", "ForwardModel",
    "PiecewiseModel", "SetModel", "finite", "forward_model", "piecewise_model",
]

SCHEMA_VERSION = 1


#: What a set says of its raw values when the session did not name their unit.
DEFAULT_RAW_UNITS = "counts"

@dataclass(frozen=True)
class CoefficientSet:
    """One axis of one sensor: zero bias, rate model, effect terms, fit statistics."""

    sensor_id: str
    axis: str
    v0: float
    model: SetModel
    terms: tuple[Term, ...] = ()
    fit: dict[str, Any] = field(default_factory=dict)
    created: str = ""
    raw_units: str = DEFAULT_RAW_UNITS  # the raw signal's unit (a DBC signal's physical unit)
    rate_units: str = "deg/s"
    schema: int = SCHEMA_VERSION

    @property
    def kind(self) -> ModelKind:
        return self.model.kind

    @property
    def span_raw(self) -> tuple[float, float]:
        lo, hi = self.model.span_raw
        return float(lo), float(hi)

    def rate_model(self) -> PiecewisePoly | ForwardPoly:
        """The run-time ΔV → ω model this set describes."""
        return self.model.rate_model(self.v0)

    def to_dict(self) -> dict[str, Any]:
        """Plain content in file order (without the CRC, which covers it)."""
        return {
            "schema": self.schema,
            "sensor": {"id": self.sensor_id, "axis": self.axis},
            "units": {"raw": self.raw_units, "rate": self.rate_units},
            "created": self.created,
            "v0": self.v0,
            "model": self.model.to_dict(),
            "terms": [t.to_dict() for t in self.terms],
            "fit": self.fit,
        }
