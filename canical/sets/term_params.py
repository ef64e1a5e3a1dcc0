"""The parameter records of effect terms: one frozen record per shape of kind, holding exactly the
fields that kind reads.

Why: a term used to be one record with five optional fields (``channel``, ``tau_s``,
``threshold_raw``, ``knots``, ``pieces``), most of them None for any one kind, so every reader
tested ``is not None`` or wrote ``or ()`` and mypy could not tell a lag's τ from a spline's knots.
Now each kind of :mod:`canical.sets.term_kinds` names its record (``TermKind.record``), a
:class:`~canical.sets.terms.Term` holds one, and a reader that does not know the kind narrows
with ``isinstance`` before it reads a field: the records of a kind with a time constant are all
:class:`Tau`, those with a threshold :class:`Threshold`, those with a piecewise cubic
:class:`Curve`, those of a channel :class:`OnChannel` (``isinstance(t.params, Tau)``, then
``t.params.tau_s``); a reader that dispatched on the kind narrows with ``TermKind.owns``.

The field names are the set file's keys: :meth:`TermParams.fields` is what a term writes for
them (see :meth:`canical.sets.terms.Term.to_dict`).
"""

from __future__ import annotations

from dataclasses import dataclass, fields
from typing import Any

__all__ = ["Curve", "Gated", "Lag", "LagSpline", "NoParams", "OnChannel", "Spline", "Tau",
           "TermParams", "Threshold"]


@dataclass(frozen=True)
class TermParams:
    """The base of every parameter record (a term's kind-specific fields)."""

    def fields(self) -> dict[str, Any]:
        """The record's fields by their set-file key, in declaration order."""
        return {f.name: getattr(self, f.name) for f in fields(self)}

    @classmethod
    def field_names(cls) -> frozenset[str]:
        """The set-file keys a record of this class holds."""
        return frozenset(f.name for f in fields(cls))


@dataclass(frozen=True)
class NoParams(TermParams):
    """A kind that reads nothing but its input (a linear drift)."""


@dataclass(frozen=True)
class Tau(TermParams):
    """A time constant (a warm-up, the raw output's smoothed slope)."""

    tau_s: float


@dataclass(frozen=True)
class Threshold(TermParams):
    """A hysteresis threshold on the raw output (the direction of approach)."""

    threshold_raw: float


@dataclass(frozen=True)
class Curve(TermParams):
    """A piecewise cubic: knots b₀ < … < b_m and one row (a₀, a₁, a₂, a₃) per segment."""

    knots: tuple[float, ...]
    pieces: tuple[tuple[float, ...], ...]


@dataclass(frozen=True)
class OnChannel(TermParams):
    """A transform of an auxiliary channel, named as the run-time input it reads."""

    channel: str


@dataclass(frozen=True)
class Lag(OnChannel, Tau):
    """A channel seen through a first-order lag of time constant ``tau_s``."""


@dataclass(frozen=True)
class Gated(OnChannel, Threshold):
    """A channel with a threshold: the gated level's knee (raw units) or the channel's direction
    hysteresis (the channel's units)."""


@dataclass(frozen=True)
class Spline(OnChannel, Curve):
    """A piecewise cubic of the channel (or of ΔV, times the channel's level)."""


@dataclass(frozen=True)
class LagSpline(Lag, Curve):
    """A piecewise cubic of the channel's lag or smoothed rate of change."""
