"""The rate model part of a coefficient set, as typed records parsed once at load.

One record per run-time form: :class:`PiecewiseModel` (the segmented kinds, ω(ΔV) over knots)
and :class:`ForwardModel` (the forward polynomial). Each holds its :class:`ModelKind` from the
registry in :mod:`canical.models.kinds`, validates its file form in :meth:`from_dict` and writes
it back in :meth:`to_dict` with the same keys, in the same order, and the numbers as they were
read (an integer stays an integer), so a set's canonical bytes, and so its CRC, survive a round
trip. Readers take these records; nothing downstream indexes the model by string.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from typing import Any, TypeGuard

import numpy as np

from canical.errors import CanicalError
from canical.models.forward_poly import ForwardPoly
from canical.models.kinds import FORWARD_POLY, MODEL_KINDS, ModelKind, model_kind
from canical.models.piecewise import PiecewisePoly

OUT_OF_SPAN_BEHAVIOUR = "linear-extrapolation"

# Builds the one-line error naming the file; each caller raises what it returns.
FailFn = Callable[[str], CanicalError]


def finite(value: object) -> TypeGuard[int | float]:
    """A real, finite number (bools excluded)."""
    if not isinstance(value, int | float) or isinstance(value, bool):
        return False
    try:
        return math.isfinite(value)
    except OverflowError:  # an integer beyond float range
        return False


@dataclass(frozen=True)
class PiecewiseModel:
    """A segmented model: ω = Σ c_k (ΔV/scale)^k per segment, knots and span in absolute raw units."""

    kind: ModelKind
    knots_raw: tuple[float, ...]
    scale: float
    coefficients: tuple[tuple[float, ...], ...]
    span_raw: tuple[float, float]
    smoothness: int | None = None
    #: None: the file has no such key (older files); a list otherwise.
    segment_points_dps: tuple[float, ...] | None = None
    out_of_span: str = OUT_OF_SPAN_BEHAVIOUR
    #: The keys the file gave, in its order (None: all, in the order canical writes them), and
    #: the values of keys this version does not read, as read (see :func:`model_from_dict`).
    keys: tuple[str, ...] | None = field(default=None, compare=False)
    unread: tuple[tuple[str, Any], ...] = field(default=(), compare=False)

    def rate_model(self, v0: float) -> PiecewisePoly:
        """The run-time ΔV → ω model, with knots and span relative to ``v0``."""
        knots = np.asarray(self.knots_raw, dtype=float) - v0
        span = (self.span_raw[0] - v0, self.span_raw[1] - v0)
        return PiecewisePoly(knots, np.asarray(self.coefficients, dtype=float), self.scale, span)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"kind": self.kind.name, "knots_raw": list(self.knots_raw)}
        if self.segment_points_dps is not None:
            out["segment_points_dps"] = list(self.segment_points_dps)
        out.update({"scale": self.scale, "coefficients": [list(row) for row in self.coefficients],
                    "smoothness": self.smoothness, "span_raw": list(self.span_raw),
                    "out_of_span": self.out_of_span})
        return _as_read(out, self.keys, self.unread)

    @classmethod
    def from_dict(cls, kind: ModelKind, model: Mapping[str, Any], fail: FailFn) -> PiecewiseModel:
        lo, hi = _span(model, fail)
        knots = _numbers(model, "knots_raw", fail)
        if any(b <= a for a, b in itertools.pairwise(knots)):
            raise fail("model.knots_raw must be strictly ascending")
        if knots and not (lo < knots[0] and knots[-1] < hi):
            raise fail("model.knots_raw must lie inside model.span_raw")
        scale = model.get("scale")
        if not finite(scale) or scale <= 0:
            raise fail("model.scale must be a positive number")
        coeffs = model.get("coefficients")
        if not isinstance(coeffs, list) or len(coeffs) != len(knots) + 1:
            raise fail(f"model.coefficients must have one row per segment ({len(knots) + 1})")
        widths = {len(r) if isinstance(r, list) else -1 for r in coeffs}
        if len(widths) != 1 or widths.pop() < 1:
            raise fail("model.coefficients rows must be lists of the same length")
        if not all(finite(c) for row in coeffs for c in row):
            raise fail("model.coefficients must be finite numbers")
        smoothness = model.get("smoothness")
        if smoothness not in (None, 0, 1):  # as before: 1.0 and true pass too, kept as read
            raise fail("model.smoothness must be null, 0 or 1")
        return cls(kind, tuple(knots), scale, tuple(tuple(row) for row in coeffs), (lo, hi), smoothness,
                   _segment_points(model, fail), _out_of_span(model, fail))


@dataclass(frozen=True)
class ForwardModel:
    """The forward polynomial: ΔV = Σ a_k (ω/rate_scale)^k over ``rate_span_dps``."""

    coefficients: tuple[float, ...]
    rate_scale: float
    rate_span_dps: tuple[float, float]
    span_raw: tuple[float, float]
    segment_points_dps: tuple[float, ...] | None = None
    out_of_span: str = OUT_OF_SPAN_BEHAVIOUR
    #: The keys the file gave, in its order, and the values of keys not read (as PiecewiseModel's).
    keys: tuple[str, ...] | None = field(default=None, compare=False)
    unread: tuple[tuple[str, Any], ...] = field(default=(), compare=False)

    @property
    def kind(self) -> ModelKind:
        return FORWARD_POLY

    def rate_model(self, v0: float) -> ForwardPoly:
        """The run-time ΔV → ω model (it works in ΔV already; ``v0`` is not needed)."""
        del v0
        return ForwardPoly(np.asarray(self.coefficients, dtype=float), self.rate_scale, self.rate_span_dps)

    def to_dict(self) -> dict[str, Any]:
        out: dict[str, Any] = {"kind": self.kind.name, "coefficients": list(self.coefficients),
                               "rate_scale": self.rate_scale, "rate_span_dps": list(self.rate_span_dps),
                               "span_raw": list(self.span_raw), "out_of_span": self.out_of_span}
        if self.segment_points_dps is not None:
            out["segment_points_dps"] = list(self.segment_points_dps)
        return _as_read(out, self.keys, self.unread)

    @classmethod
    def from_dict(cls, kind: ModelKind, model: Mapping[str, Any], fail: FailFn) -> ForwardModel:
        del kind  # one kind has this form
        span = _span(model, fail)
        coeffs = _numbers(model, "coefficients", fail)
        if len(coeffs) < 2:
            raise fail("model.coefficients needs at least 2 entries")
        rate_scale = model.get("rate_scale")
        if not finite(rate_scale) or rate_scale <= 0:
            raise fail("model.rate_scale must be a positive number")
        w_lo, w_hi = _numbers(model, "rate_span_dps", fail, length=2)
        if not w_lo < w_hi:
            raise fail("model.rate_span_dps must be ascending")
        return cls(tuple(coeffs), rate_scale, (w_lo, w_hi), span, _segment_points(model, fail),
                   _out_of_span(model, fail))


#: A set's rate model, whichever its kind.
SetModel = PiecewiseModel | ForwardModel


def model_from_dict(model: Mapping[str, Any], fail: FailFn) -> SetModel:
    """Validate a file's ``model`` mapping into its record; a defect is one line from ``fail``."""
    kind = model_kind(model.get("kind"))
    if kind is None:
        raise fail(f"model.kind {model.get('kind')!r} unknown (known: {', '.join(MODEL_KINDS)})")
    record = PiecewiseModel if kind.piecewise else ForwardModel
    parsed = record.from_dict(kind, model, fail)
    written = parsed.to_dict()
    # The record writes back what it read: the keys in the file's order, a key left out (its
    # default) left out, and a key this version does not read (a newer version's, knots on the
    # forward polynomial) with its value as read; so the set's bytes and CRC stay the file's.
    unread = tuple((str(k), v) for k, v in model.items()
                   if k not in written or v != written[k] or type(v) is not type(written[k]))
    keys = tuple(str(k) for k in model)
    return parsed if keys == tuple(written) and not unread else replace(parsed, keys=keys, unread=unread)


def _as_read(out: dict[str, Any], keys: tuple[str, ...] | None,
             unread: tuple[tuple[str, Any], ...]) -> dict[str, Any]:
    if keys is None:
        return out
    values = dict(unread)
    return {k: values[k] if k in values else out[k] for k in keys}


def piecewise_model(kind: ModelKind, poly: PiecewisePoly, v0: float, *, smoothness: int | None,
                    segment_points_dps: Sequence[float]) -> PiecewiseModel:
    """The set's model for a fitted segmented model, knots and span in absolute raw units."""
    return PiecewiseModel(
        kind,
        tuple(float(k + v0) for k in poly.knots),
        float(poly.scale),
        tuple(tuple(float(c) for c in row) for row in poly.coeffs),
        (float(poly.span[0] + v0), float(poly.span[1] + v0)),
        smoothness,
        tuple(float(w) for w in segment_points_dps),
    )


def forward_model(model: ForwardPoly, v0: float) -> ForwardModel:
    """The set's model for a fitted forward polynomial."""
    lo, hi = model.span
    return ForwardModel(tuple(float(c) for c in model.coeffs), float(model.rate_scale),
                        (float(model.rate_span[0]), float(model.rate_span[1])),
                        (float(lo + v0), float(hi + v0)))


def _numbers(model: Mapping[str, Any], key: str, fail: FailFn, *, length: int | None = None) -> list[float]:
    values = model.get(key)
    if not isinstance(values, list) or not all(finite(v) for v in values):
        raise fail(f"model.{key} must be a list of finite numbers")
    if length is not None and len(values) != length:
        raise fail(f"model.{key} must have {length} entries, has {len(values)}")
    return values


def _span(model: Mapping[str, Any], fail: FailFn) -> tuple[float, float]:
    lo, hi = _numbers(model, "span_raw", fail, length=2)
    if not lo < hi:
        raise fail("model.span_raw must be ascending [low, high]")
    return lo, hi


def _segment_points(model: Mapping[str, Any], fail: FailFn) -> tuple[float, ...] | None:
    if "segment_points_dps" not in model:
        return None
    return tuple(_numbers(model, "segment_points_dps", fail))


def _out_of_span(model: Mapping[str, Any], fail: FailFn) -> str:
    """What the file says happens beyond the span (informative: the behaviour is the model's; a
    value that is not a string is kept as read, unread)."""
    del fail
    value = model.get("out_of_span", OUT_OF_SPAN_BEHAVIOUR)
    return value if isinstance(value, str) else OUT_OF_SPAN_BEHAVIOUR


def model_of(model: Mapping[str, Any], source: str = "<model>") -> SetModel:
    """A model mapping written in code (tests, tools) as its record; a defect is one line."""

    def fail(msg: str) -> CanicalError:
        return CanicalError(f"{source}: {msg}")

    return model_from_dict(model, fail)
