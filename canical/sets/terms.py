"""Effect terms: what the closed loop adds to a rate model, evaluated at run time.

Effects act on the sensor's output, so their correction is applied there, in
raw units, before the rate model: for a term with feature x,

* ``bias`` form:  ΔV' = ΔV − c·x        (c in raw units per unit of x),
* ``scale`` form: ΔV' = ΔV − c·x·ΔV     (c: relative gain error per unit of x),

and then ω = f(ΔV'). Correcting in the rate domain instead would be wrong by
the slope variation of f (a few per cent for a nonlinear sensor) times the
effect. The coefficient is the sensor's own error, so a positive temperature
coefficient means the output rises with temperature. Features:

* ``channel`` — an auxiliary signal by name, minus its reference value:
  ``offset`` x = v − ref, ``square`` x = (v − ref)²; and, with state (the sensor
  feels the channel late or through its changes; input ``time_s`` too for the
  first two): ``lag`` x = y − ref where y follows v through a first-order lag of
  time constant τ (the die is where the effect acts, the channel reads elsewhere),
  ``derivative`` x = (v − y)/τ, the rate of change of v smoothed with τ (a thermal
  transient; for the first τ of a stream y is the mean of the samples so far),
  ``direction`` x = ±1, the sign of the last change of v larger than
  ``threshold_raw`` in the channel's own units (hysteresis: heating vs cooling);
  and, stateless but reading the raw output too, ``gated`` x = (v − ref)·g with
  g = max(|ΔV| − k, 0)/|ΔV| and the knee k = ``threshold_raw`` in raw units: an
  effect that acts only beyond some rate (a drive loop near its limit). In scale
  form c·x·ΔV = c·(v − ref)·sign(ΔV)·max(|ΔV| − k, 0), a hinge; in bias form a
  bias that switches on with rate; and ``spline`` x = S(v), a piecewise cubic of the
  channel learned from the data (``knots``, ``pieces``; flat beyond the end knots): a
  smooth effect whose form is none of the above (the C evaluator runs it too: a
  binary search over the knots and the same cubic, in float32); ``rate_spline``
  x = (v − ref)·R(ΔV), its level times a piecewise cubic of the output; ``lag_spline``
  x = S(y) and ``derivative_spline`` x = S((v − y)/τ), the same piecewise cubic of the
  channel's lag or of its smoothed rate of change (τ and ``time_s`` as for ``lag``);
* ``time`` — time since power-on t (input ``time_s``): ``warmup`` x = 1 − exp(−t/τ),
  ``linear`` x = t;
* ``direction`` — how the rate got where it is. ``sign``: the direction of the last
  significant change of the raw output (x = +1 after a rise, −1 after a fall, 0
  before either), a hysteresis tracker with a threshold in raw units. ``slope``:
  the rate of change of the raw output (raw units per second, smoothed with time
  constant τ; input ``time_s``). Both have state, so samples must come in time order.

Terms are plain dicts in the coefficient file (see :data:`TERM_FIELDS`); this
module validates them into :class:`Term` records and evaluates their features for a
block of samples. What each kind is, reads and computes lives in one object per kind
in :mod:`canical.sets.term_kinds`; the trackers are :mod:`canical.sets.trackers`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from itertools import pairwise
from typing import TYPE_CHECKING, Any, Generic, Protocol, TypeGuard, TypeVar

import numpy as np

from canical.sets.term_kinds import (
    ALL,
    CHANNEL,
    FEATURES,
    MAX_SPLINE_KNOTS,
    TIME_INPUT,
    TermKind,
    TermWording,
    gated_name,
    lookup,
)
from canical.sets.term_params import Curve, OnChannel, TermParams
from canical.sets.trackers import (
    ChannelTracker,
    DirectionTracker,
    SlopeTracker,
    direction_state,
    gate_one,
    lag_filter,
    rate_gate,
    slope_state,
)

__all__ = [
    "FEATURES", "FORMS", "STATEFUL_CHANNEL", "TERM_FIELDS", "TIME_INPUT", "ChannelTracker",
    "DirectionTracker", "SlopeTracker", "Term", "direction_state",
    "feature_values", "gate_one", "gated_name", "lag_filter", "merge_splines", "rate_gate", "raw_shift",
    "slope_state", "spline_group", "term_from_dict", "term_from_file",
]

FORMS = ("bias", "scale")
#: The channel features with state (a lag, a derivative, a direction).
STATEFUL_CHANNEL = tuple(k.feature for k in ALL if k.kind == CHANNEL and k.tracker_type is not None)
#: Bounds on a term's time constant. Why: below a microsecond (far under any sample interval) or
#: beyond 30 years it describes no sensor, and a τ of 5e-324 s made t/τ overflow (numpy warned on
#: every block; a negative time would give an infinite warm-up factor).
MIN_TAU_S = 1e-6
MAX_TAU_S = 1e9
TERM_FIELDS = ("kind", "channel", "feature", "form", "coefficient", "reference", "tau_s", "threshold_raw",
               "knots", "pieces")


if TYPE_CHECKING:  # with a default (PEP 696, typing_extensions on 3.11): a bare ``Term`` is of any kind
    import typing_extensions

    P_co = typing_extensions.TypeVar("P_co", bound=TermParams, covariant=True, default=TermParams)
else:
    P_co = TypeVar("P_co", bound=TermParams, covariant=True)
P = TypeVar("P", bound=TermParams)
R_co = TypeVar("R_co", bound=TermParams, covariant=True)


class Recorded(Protocol[R_co]):
    """A kind as :meth:`Term.of` reads it: the record its terms hold. Why a protocol: read-only,
    it is covariant, so mypy infers a lag's record for ``Term.of(CHANNEL_LAG, …)`` even where the
    call stands as an argument taking any term (:class:`TermKind` itself is invariant)."""

    @property
    def record(self) -> type[R_co]: ...


@dataclass(frozen=True)
class Term(Generic[P_co]):
    """One validated term: the common core (kind object, form, coefficient, reference) and its
    kind's parameter record (``params``, exactly the fields the kind reads). What the term is,
    reads and computes is asked of the kind object (``spec``), never looked up again by the
    file's strings; a reader that does not know the kind narrows ``params`` with ``isinstance``."""

    spec: TermKind[Any]
    form: str
    coefficient: float
    params: P_co
    reference: float = 0.0
    #: The keys a set file gave the term, in its order (None: all of them, in :data:`TERM_FIELDS`
    #: order), and the values of those this kind does not read (a key of a newer version, a
    #: channel on a time term), as read. Why: a file that leaves a key out, or carries one this
    #: version ignores, is written back as it was, so the set's bytes and CRC stay the file's.
    keys: tuple[str, ...] | None = field(default=None, compare=False)
    unread: tuple[tuple[str, Any], ...] = field(default=(), compare=False)

    def __post_init__(self) -> None:
        """Why: mypy ties a term's record to its kind where the kind is known (:meth:`of`); this
        holds it where it is not (a kind looked up from a file, a record replaced)."""
        if type(self.params) is not self.spec.record:
            raise TypeError(f"a {self.spec!r} term holds a {self.spec.record.__name__}, "
                            f"not a {type(self.params).__name__}")

    @classmethod
    def of(cls, spec: Recorded[P], form: str, coefficient: float, reference: float = 0.0,
           **fields: Any) -> Term[P]:
        """A term of the registry's kind ``spec``, its record built from ``fields`` (a field the
        kind does not read is a TypeError)."""
        if not isinstance(spec, TermKind):
            raise TypeError(f"{spec!r} is not a term kind")
        return Term(spec, form, coefficient, spec.record(**fields), reference)

    @property
    def kind(self) -> str:
        """The kind's name in the set file (``channel``, ``time``, ``direction``)."""
        return self.spec.kind

    @property
    def feature(self) -> str:
        """The feature's name in the set file (``offset``, ``lag``, ``warmup``, …)."""
        return self.spec.feature

    @property
    def channel(self) -> str | None:
        """The auxiliary channel the term transforms (None: a time or direction term)."""
        return self.params.channel if isinstance(self.params, OnChannel) else None

    @property
    def input_name(self) -> str | None:
        """The run-time input this term reads first (None: derived from raw alone)."""
        return self.spec.input_name(self)

    @property
    def input_names(self) -> tuple[str, ...]:
        """Every run-time input this term reads: a lag or derivative needs time as well."""
        return self.spec.input_names(self)

    def describe(self) -> str:
        """A readable name for reports: ``d/dt temp_c``, ``lag(temp_c, τ=140 s)``."""
        wording: TermWording = self.spec
        return wording.describe(self)

    def to_dict(self) -> dict[str, Any]:
        """The set file's term; ``knots`` and ``pieces`` only for a spline (other terms' bytes,
        and so their sets' CRCs, stay what they were); a field the kind does not read is null."""
        params = self.params.fields()
        out: dict[str, Any] = {
            "kind": self.kind,
            "channel": params.get("channel"),
            "feature": self.feature,
            "form": self.form,
            "coefficient": self.coefficient,
            "reference": self.reference,
            "tau_s": params.get("tau_s"),
            "threshold_raw": params.get("threshold_raw"),
        }
        if isinstance(self.params, Curve):
            out["knots"] = list(self.params.knots)
            out["pieces"] = [list(row) for row in self.params.pieces]
        if self.keys is None:
            return out
        unread = dict(self.unread)
        return {k: unread[k] if k in unread else out[k] for k in self.keys}


def term_from_dict(d: Mapping[str, Any], where: str = "term") -> Term:
    """Validate a term dict; raises ValueError with a message naming the field."""
    kind = d.get("kind")
    if not isinstance(kind, str) or kind not in FEATURES:
        raise ValueError(f"{where}: kind {kind!r} not supported by this canical version")
    feature = d.get("feature")
    spec = lookup(kind, feature) if isinstance(feature, str) else None
    if spec is None:
        raise ValueError(
            f"{where}: feature {feature!r} not valid for kind {kind} ({', '.join(FEATURES[kind])})"
        )
    form = d.get("form")
    if form not in FORMS:
        raise ValueError(f"{where}: form {form!r} must be bias or scale")

    def number(key: str, required: bool = False, positive: bool = False) -> float | None:
        v = d.get(key)
        if v is None and not required:
            return None
        if not _finite(v):
            raise ValueError(f"{where}: {key} must be a finite number")
        if positive and v <= 0:
            raise ValueError(f"{where}: {key} must be positive")
        number: float = v  # as read, an integer too: the set's bytes (and CRC) are the file's
        return number

    channel = d.get("channel")
    if spec.needs_channel and (not isinstance(channel, str) or not channel):
        raise ValueError(f"{where}: channel must name an input")
    tau = number("tau_s", required=spec.needs_tau, positive=True)
    if tau is not None and not MIN_TAU_S <= tau <= MAX_TAU_S:
        raise ValueError(f"{where}: tau_s {tau:.3g} s is outside {MIN_TAU_S:g}..{MAX_TAU_S:g} s: "
                         "not a time constant a sensor has")
    threshold = number("threshold_raw", required=spec.needs_threshold, positive=True)
    knots, pieces = _spline_fields(d, where) if spec.needs_spline else (None, None)
    coefficient = number("coefficient", required=True)
    assert coefficient is not None  # required: number() raised otherwise
    reference = number("reference")
    read = {"channel": channel, "tau_s": tau, "threshold_raw": threshold, "knots": knots, "pieces": pieces}
    params = spec.record(**{key: read[key] for key in spec.record.field_names()})
    return Term(spec, form, coefficient, params, 0.0 if reference is None else reference)


def term_from_file(d: Mapping[str, Any], where: str) -> Term:
    """A set file's term: validated as :func:`term_from_dict` does, and holding what the record
    would not write back by itself (its keys' order, keys left out, values its kind does not
    read), so that it writes back the file's bytes and the loaded set's CRC is the file's."""
    term = term_from_dict(d, where)
    written = term.to_dict()
    unread = tuple((str(k), v) for k, v in d.items()
                   if k not in written or v != written[k] or type(v) is not type(written[k]))
    keys = tuple(str(k) for k in d)
    return term if keys == tuple(written) and not unread else replace(term, keys=keys, unread=unread)


def _finite(v: object) -> TypeGuard[int | float]:
    return isinstance(v, int | float) and not isinstance(v, bool) and math.isfinite(v)


def _spline_fields(d: Mapping[str, Any], where: str
                   ) -> tuple[tuple[float, ...], tuple[tuple[float, ...], ...]]:
    """A spline's knots (2 to MAX_SPLINE_KNOTS finite numbers, strictly increasing) and pieces
    (one row of 4 finite numbers per segment)."""
    knots, pieces = d.get("knots"), d.get("pieces")
    if (not isinstance(knots, list) or not 2 <= len(knots) <= MAX_SPLINE_KNOTS
            or not all(_finite(k) for k in knots)):
        raise ValueError(f"{where}: knots must be a list of 2 to {MAX_SPLINE_KNOTS} finite numbers")
    if any(not b > a for a, b in pairwise(knots)):
        raise ValueError(f"{where}: knots must be strictly increasing")
    if not isinstance(pieces, list) or len(pieces) != len(knots) - 1:
        raise ValueError(f"{where}: pieces must be a list of {len(knots) - 1} rows (one per segment)")
    for i, row in enumerate(pieces):
        if not isinstance(row, list) or len(row) != 4 or not all(_finite(a) for a in row):
            raise ValueError(f"{where}: pieces[{i}] must be 4 finite numbers (a0 a1 a2 a3)")
    return tuple(knots), tuple(tuple(row) for row in pieces)  # as read (see number())


def spline_group(t: Term) -> tuple[Any, ...]:
    """What the basis functions of one learned spline share: all but their pieces and coefficient."""
    shared = {k: v for k, v in t.params.fields().items() if k != "pieces"}
    return (t.spec, t.form, t.reference, tuple(shared.items()))


def merge_splines(terms: tuple[Term, ...]) -> tuple[Term, ...]:
    """The terms with each group of splines (:func:`spline_group`) written as one: Σ c_j·S_j is one
    piecewise cubic with pieces Σ c_j·pieces_j and coefficient 1 (of a channel, or of ΔV times
    the same channel level).

    Why: the closed loop fits a spline as one term per basis function; the set needs one segment
    lookup and one cubic per sample, not one per basis function. The merged term gives the same
    correction to rounding (the sum is taken over pieces instead of over terms). The merged term
    stands where the group's first term stood.
    """
    groups: dict[Any, list[Term]] = {}
    for j, t in enumerate(terms):
        groups.setdefault(spline_group(t) if isinstance(t.params, Curve) else j, []).append(t)
    return tuple(_merged(group) for group in groups.values())


def _merged(group: list[Term]) -> Term:
    """One group's terms as one (:func:`merge_splines`)."""
    first = group[0]
    if len(group) == 1 or not isinstance(first.params, Curve):
        return first
    rows = [t.coefficient * np.asarray(t.params.pieces, dtype=float)
            for t in group if isinstance(t.params, Curve)]
    pieces = tuple(tuple(float(a) for a in row) for row in np.asarray(sum(rows)))
    return replace(first, coefficient=1.0, params=replace(first.params, pieces=pieces))


def feature_values(
    term: Term, inputs: Mapping[str, np.ndarray], raw: np.ndarray, dv: np.ndarray | None = None
) -> np.ndarray:
    """The term's feature x for a block of samples in time order (fresh state).

    ``dv`` (raw − V0) is needed by a gated term only.
    """
    return term.spec.values(term, inputs, raw, dv)


def raw_shift(terms: tuple[Term, ...], features: np.ndarray, dv: np.ndarray) -> np.ndarray:
    """Σ c·x (bias) + Σ c·x·ΔV (scale): what the effects add to ΔV, for a block of samples.

    ``features`` holds one column per term (the feature x of each sample).
    """
    shift = np.zeros_like(dv, dtype=float)
    for j, term in enumerate(terms):
        x = features[:, j]
        shift = shift + term.coefficient * (x * dv if term.form == "scale" else x)
    return shift
