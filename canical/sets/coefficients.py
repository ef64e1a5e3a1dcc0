"""The coefficient set: the one artefact that leaves a calibration.

Plain, serialisable data (see :mod:`canical.sets.coefficient_file` for YAML and the
CRC), separate from the code that computes it and from the code that applies it.
The model part is kind-specific; ``terms`` carries effect terms added by the
closed loop (empty for a plain model). Older files that lack newer optional
keys still load; a file naming a term kind this version does not know is refused.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any, TypeGuard

import numpy as np

from canical.models.forward_poly import ForwardPoly
from canical.models.piecewise import PiecewisePoly

SCHEMA_VERSION = 1
PIECEWISE_KINDS = ("segmented-inverse", "segmented-linear")
OUT_OF_SPAN_BEHAVIOUR = "linear-extrapolation"


#: What a set says of its raw values when the session did not name their unit.
DEFAULT_RAW_UNITS = "counts"

@dataclass(frozen=True)
class CoefficientSet:
    """One axis of one sensor: zero bias, rate model, effect terms, fit statistics."""

    sensor_id: str
    axis: str
    v0: float
    model: dict[str, Any]
    terms: tuple[dict[str, Any], ...] = ()
    fit: dict[str, Any] = field(default_factory=dict)
    created: str = ""
    raw_units: str = DEFAULT_RAW_UNITS  # the raw signal's unit (a DBC signal's physical unit)
    rate_units: str = "deg/s"
    schema: int = SCHEMA_VERSION

    @property
    def kind(self) -> str:
        return str(self.model["kind"])

    @property
    def span_raw(self) -> tuple[float, float]:
        lo, hi = self.model["span_raw"]
        return float(lo), float(hi)

    def rate_model(self) -> PiecewisePoly | ForwardPoly:
        """The run-time ΔV → ω model this set describes."""
        m = self.model
        if self.kind in PIECEWISE_KINDS:
            knots = np.asarray(m["knots_raw"], dtype=float) - self.v0
            span = (self.span_raw[0] - self.v0, self.span_raw[1] - self.v0)
            return PiecewisePoly(knots, np.asarray(m["coefficients"], dtype=float), m["scale"], span)
        return ForwardPoly(
            np.asarray(m["coefficients"], dtype=float), m["rate_scale"], tuple(m["rate_span_dps"])
        )

    def to_dict(self) -> dict[str, Any]:
        """Plain content in file order (without the CRC, which covers it)."""
        return {
            "schema": self.schema,
            "sensor": {"id": self.sensor_id, "axis": self.axis},
            "units": {"raw": self.raw_units, "rate": self.rate_units},
            "created": self.created,
            "v0": self.v0,
            "model": self.model,
            "terms": [dict(t) for t in self.terms],
            "fit": self.fit,
        }


def piecewise_model_dict(
    kind: str,
    poly: PiecewisePoly,
    v0: float,
    *,
    smoothness: int | None,
    segment_points_dps: list[float],
) -> dict[str, Any]:
    """Model part of a set for a segmented model, segment points in absolute raw units."""
    return {
        "kind": kind,
        "knots_raw": [float(k + v0) for k in poly.knots],
        "segment_points_dps": [float(w) for w in segment_points_dps],
        "scale": float(poly.scale),
        "coefficients": [[float(c) for c in row] for row in poly.coeffs],
        "smoothness": smoothness,
        "span_raw": [float(poly.span[0] + v0), float(poly.span[1] + v0)],
        "out_of_span": OUT_OF_SPAN_BEHAVIOUR,
    }


def forward_model_dict(model: ForwardPoly, v0: float) -> dict[str, Any]:
    """Model part of a set for the forward polynomial."""
    lo, hi = model.span
    return {
        "kind": "forward-poly",
        "coefficients": [float(c) for c in model.coeffs],
        "rate_scale": float(model.rate_scale),
        "rate_span_dps": [float(model.rate_span[0]), float(model.rate_span[1])],
        "span_raw": [float(lo + v0), float(hi + v0)],
        "out_of_span": OUT_OF_SPAN_BEHAVIOUR,
    }


def finite(value: object) -> TypeGuard[int | float]:
    """A real, finite number (bools excluded)."""
    if not isinstance(value, int | float) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:  # an integer beyond float range
        return False
