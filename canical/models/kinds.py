"""The model-kind registry: every calibration model a set can name, one object per kind.

Why a registry: the kind's name is the file format's word for it, and code that branched on the
string in several modules had to be found and changed together to add a kind. Here each kind is
one :class:`ModelKind`; other modules compare the objects (``spec.kind is SEGMENTED_INVERSE``) or
ask the object, and the names appear nowhere else. Kept free of numpy: ``canical calibrate
--help`` lists :data:`MODEL_KINDS` at start-up.
"""

from __future__ import annotations

from dataclasses import dataclass


@dataclass(frozen=True)
class ModelKind:
    """One calibration model: its name in files and options, and the run-time form it yields."""

    name: str
    #: A piecewise polynomial ω(ΔV) over knots (True) or one forward polynomial ΔV(ω) (False).
    piecewise: bool
    #: Whether the segment points are chosen by the fit (at the extrema) rather than given.
    chooses_segment_points: bool = False

    def __str__(self) -> str:
        return self.name


SEGMENTED_INVERSE = ModelKind("segmented-inverse", piecewise=True, chooses_segment_points=True)
SEGMENTED_LINEAR = ModelKind("segmented-linear", piecewise=True)
FORWARD_POLY = ModelKind("forward-poly", piecewise=False)

#: Every kind, the default (and the one the closed loop extends) first.
ALL_KINDS = (SEGMENTED_INVERSE, SEGMENTED_LINEAR, FORWARD_POLY)
MODEL_KINDS = tuple(k.name for k in ALL_KINDS)
_BY_NAME = {k.name: k for k in ALL_KINDS}


def model_kind(name: object) -> ModelKind | None:
    """The kind a file or an option names (None: not one this version knows)."""
    return _BY_NAME.get(name) if isinstance(name, str) else None
