"""The registry of term kinds: each (kind, feature) of an effect term is one object here.

Why: a term kind used to be a pair of strings that the validation, the corrector's two paths,
the compiled corrector, the candidate search, the reports, the C evaluator and the benchmarks
each spelled and dispatched on; a kind added later was missed in one of them. Now each kind is
one object that knows

* its names in the set file (``kind``, ``feature``) and its C form's identifier (``c_name``,
  a ``CE_TERM_*`` code of ``firmware/canical_eval.c``'s ``TERM_SPECS``, which a test compares
  with :data:`ALL`);
* its parameter record (``record``, :mod:`canical.sets.term_params`: exactly the fields it
  reads, so ``needs_tau`` and the like are read off it) and the run-time inputs it reads
  (:meth:`TermKind.input_names`). ``TermKind`` is generic over its record: each kind's methods
  take a ``Term`` of its own record, and mypy checks they read only its fields; a reader that
  dispatched on the kind narrows a term with :meth:`TermKind.owns`;
* its state tracker (:meth:`TermKind.tracker`) and its feature x, for a block of samples
  (:meth:`TermKind.values`) and for one sample (:meth:`TermKind.one`), the same operations
  in the same order;
* the statements the compiled corrector writes for it (:meth:`TermKind.code`), and whether
  the compiled corrector may keep the part of x that depends on its input alone between
  frames (``kept``: the kind is a :class:`KeptCode`, :meth:`kept_x`);
* its description in reports (:meth:`TermKind.describe`) and a channel transform's name as a
  candidate (:meth:`ChannelKind.label`);
* how large x can get for bounded inputs (:meth:`TermKind.reach`), so that loading a set can
  prove its outputs finite.

Each kind's contract is three narrow protocols, so a reader depends on the part it uses only:
:class:`TermMaths` (inputs, state, x, reach: the corrector and the load-time proof),
:class:`TermCode` (the compiled corrector's statements; :class:`KeptCode` for the kinds whose x
may be kept between frames) and :class:`TermWording` (the report's name). The base class
:class:`TermKind` is abstract: a kind that leaves one of its parts out cannot be instantiated,
so the registry fails at import rather than a reader at run time (no ``NotImplementedError``).

Adding a kind is one new class here (and one row plus one ``case`` in the C evaluator); the
tests fail while any of these is missing. A kind with ``c_name`` None is not (yet) in the C
evaluator: the device would refuse a set holding it, so ``canical push`` refuses to send it
(:func:`host_only`). Every kind of this version has its C form, the splines included (the
firmware's ``spline_at``: the same clamp, segment lookup and Horner steps as :func:`spline_one`).
Like cantools' conversions: one class per kind
behind a lookup (:func:`lookup`). The term record itself, and the set file's validation built
on these objects, are :mod:`canical.sets.terms`.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from bisect import bisect_right
from collections.abc import Mapping
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any, ClassVar, Generic, Protocol, TypeGuard, TypeVar, runtime_checkable

import numpy as np

from canical.sets.term_params import (
    Curve,
    Gated,
    Lag,
    LagSpline,
    NoParams,
    OnChannel,
    Spline,
    Tau,
    TermParams,
    Threshold,
)
from canical.sets.trackers import (
    ChannelTracker,
    DirectionTracker,
    SlopeTracker,
    direction_state,
    gate_one,
    rate_gate,
    slope_state,
)

if TYPE_CHECKING:
    from canical.sets.terms import Term

#: The run-time input holding time since power-on (seconds).
TIME_INPUT = "time_s"
#: The kinds (groups of features) a set file names.
CHANNEL = "channel"
TIME = "time"
DIRECTION = "direction"

Tracker = ChannelTracker | DirectionTracker | SlopeTracker
#: Inputs for a block of samples, and for one sample.
Block = Mapping[str, np.ndarray]
Sample = Mapping[str, float]
#: A kind's parameter record; a channel kind's, a lagged channel kind's.
P = TypeVar("P", bound=TermParams)
C = TypeVar("C", bound=OnChannel)
L = TypeVar("L", bound=Lag)


@dataclass(frozen=True)
class CodeNames:
    """What the compiled corrector's statements for one term refer to: the expressions of the
    term's input, of time and of the raw value, and the name its tracker's ``update`` is bound to."""

    value: str
    time: str
    raw: str
    track: str


def _column(inputs: Block, name: str) -> np.ndarray:
    """An input as floats."""
    return np.asarray(inputs[name], dtype=float)


def _offset_times(term: Term[OnChannel], inputs: Block, factor: np.ndarray) -> np.ndarray:
    """(v − ref)·factor for a block: a channel's level acting through a function of the output."""
    out: np.ndarray = (_column(inputs, term.params.channel) - term.reference) * factor
    return out


def share(term: Term, x: str) -> str:
    """The compiled line adding ``term``'s share c·x (bias) or c·x·ΔV (scale) to the shift."""
    return f"    shift += {term.coefficient!r} * " + (f"({x} * dv)" if term.form == "scale" else f"{x}")


class TermMaths(Protocol):
    """What the corrector and the load-time proof need of a kind: its inputs, state and feature x."""

    def input_names(self, term: Term) -> tuple[str, ...]: ...

    def tracker(self, term: Term) -> Tracker | None: ...

    def values(self, term: Term, inputs: Block, raw: np.ndarray, dv: np.ndarray | None) -> np.ndarray: ...

    def values_from(self, term: Term, tracker: Any, inputs: Block, raw: np.ndarray,
                    dv: np.ndarray | None) -> np.ndarray: ...

    def one(self, term: Term, tracker: Any, raw: float, dv: float, inputs: Sample) -> float: ...

    def reach(self, term: Term, inputs: float) -> float: ...


class TermCode(Protocol):
    """What the compiled corrector needs of a kind: the statements adding the term's share."""

    def code(self, term: Term, names: CodeNames) -> list[str]: ...


@runtime_checkable
class KeptCode(Protocol):
    """A kind whose x the compiled corrector may keep between frames: x of its input alone."""

    def kept_x(self, term: Term, value: str) -> str: ...


class TermWording(Protocol):
    """What a report needs of a kind: a readable name for a term of it."""

    def describe(self, term: Term) -> str: ...


class TermKind(ABC, Generic[P]):
    """One (kind, feature) of effect term: its names, the fields it needs, and the three parts a
    kind supplies (:class:`TermMaths`, :class:`TermCode`, :class:`TermWording`); each concrete
    kind implements every abstract method (instantiating one that does not fails at import)."""

    kind: ClassVar[str]
    feature: ClassVar[str]
    #: The C evaluator's code; None: the C evaluator refuses a set with this kind
    #: (``CE_ERR_TERM_KIND``), and ``canical push`` refuses to send it.
    c_name: ClassVar[str | None]
    #: The parameter record a term of this kind holds: exactly the fields the kind reads.
    record: type[P]
    #: The tracker class this kind keeps its state in (None: stateless).
    tracker_type: ClassVar[type | None] = None
    #: Whether x is computed from the raw output itself (its tracker gets the raw value).
    reads_raw: ClassVar[bool] = False

    @property
    def key(self) -> tuple[str, str]:
        return (self.kind, self.feature)

    @property
    def needs_channel(self) -> bool:
        return issubclass(self.record, OnChannel)

    @property
    def needs_tau(self) -> bool:
        return "tau_s" in self.record.field_names()

    @property
    def needs_threshold(self) -> bool:
        return "threshold_raw" in self.record.field_names()

    @property
    def needs_spline(self) -> bool:
        """Whether the term carries a piecewise cubic (``knots``, ``pieces``)."""
        return issubclass(self.record, Curve)

    @property
    def kept(self) -> bool:
        """Whether the compiled corrector keeps the part of x that depends on the input alone."""
        return isinstance(self, KeptCode)

    def __repr__(self) -> str:
        return f"<term kind {self.kind}/{self.feature}>"

    def owns(self, term: Term) -> TypeGuard[Term[P]]:
        """Whether ``term`` is of this kind; if so, mypy knows its record is this kind's."""
        return term.spec is self

    def __reduce__(self) -> tuple[Any, tuple[str, str]]:
        """Pickled and copied as the registry's own object (a term held across processes, or
        deep-copied, still holds the one instance its kind is compared by)."""
        return (registered, self.key)

    def input_names(self, term: Term[P]) -> tuple[str, ...]:
        """Every run-time input the term reads, the first its own (:meth:`input_name`)."""
        return ()

    def input_name(self, term: Term[P]) -> str | None:
        """The run-time input this term reads first (None: derived from raw alone)."""
        names = self.input_names(term)
        return names[0] if names else None

    def tracker(self, term: Term[P]) -> Tracker | None:
        """A fresh state for one stream of samples (None: the kind has none)."""
        return None

    @abstractmethod
    def values(self, term: Term[P], inputs: Block, raw: np.ndarray, dv: np.ndarray | None) -> np.ndarray:
        """x for a block of samples in time order, from a fresh state."""

    def values_from(self, term: Term[P], tracker: Any, inputs: Block, raw: np.ndarray,
                    dv: np.ndarray | None) -> np.ndarray:
        """x for the next block of the stream whose state ``tracker`` holds (left at the block's end).

        Why: ``canical apply`` corrects a long file block by block, and every split of a stream
        into blocks must give what one block gives. A stateless kind ignores ``tracker``.
        """
        return self.values(term, inputs, raw, dv)

    @abstractmethod
    def one(self, term: Term[P], tracker: Any, raw: float, dv: float, inputs: Sample) -> float:
        """x for the next sample of the stream whose state ``tracker`` holds."""

    @abstractmethod
    def code(self, term: Term[P], names: CodeNames) -> list[str]:
        """The compiled corrector's statements adding this term's share to ``shift``."""

    @abstractmethod
    def describe(self, term: Term[P]) -> str:
        """A readable name for reports."""

    def reach(self, term: Term[P], inputs: float) -> float:
        """The largest |x| while every input (and the raw output's rate of change) stays within
        ±``inputs``: what bounds the term's share (see :mod:`canical.sets.finite_outputs`)."""
        return 1.0  # a direction, a warm-up: within ±1 whatever the inputs


class SharedCode(TermKind[P]):
    """A kind whose x is one expression (:meth:`code_x`): its code is the share c·x or c·x·ΔV."""

    def code(self, term: Term[P], names: CodeNames) -> list[str]:
        return [share(term, self.code_x(term, names))]

    @abstractmethod
    def code_x(self, term: Term[P], names: CodeNames) -> str:
        """x as one expression of the compiled corrector."""


class ChannelKind(TermKind[C]):
    """A transform of an auxiliary channel v (minus its reference value)."""

    kind = CHANNEL

    def input_names(self, term: Term[C]) -> tuple[str, ...]:
        return (term.params.channel,)

    @abstractmethod
    def label(self, channel: str, tau_s: float | None = None) -> str:
        """How a report or a candidate names this transform of ``channel``."""

    def describe(self, term: Term[C]) -> str:
        return self.label(term.params.channel)

    def reach(self, term: Term[C], inputs: float) -> float:
        return inputs + abs(term.reference)  # a level, a lag of it, a gated level: |v − ref|


class ChannelOffset(ChannelKind[OnChannel], SharedCode[OnChannel]):
    """x = v − ref."""

    feature = "offset"
    c_name = "CE_TERM_CHANNEL_OFFSET"
    record = OnChannel

    def values(self, term: Term[OnChannel], inputs: Block,
               raw: np.ndarray, dv: np.ndarray | None) -> np.ndarray:
        out: np.ndarray = _column(inputs, term.params.channel) - term.reference
        return out

    def one(self, term: Term[OnChannel], tracker: Any, raw: float, dv: float, inputs: Sample) -> float:
        return float(inputs[term.params.channel]) - term.reference

    def code_x(self, term: Term[OnChannel], names: CodeNames) -> str:
        return f"({names.value} - {term.reference!r})"

    def kept_x(self, term: Term[OnChannel], value: str) -> str:
        return f"({value} - {term.reference!r})"

    def label(self, channel: str, tau_s: float | None = None) -> str:
        return f"{CHANNEL}:{channel}"


class ChannelSquare(ChannelKind[OnChannel]):
    """x = (v − ref)²."""

    feature = "square"
    c_name = "CE_TERM_CHANNEL_SQUARE"
    record = OnChannel

    def values(self, term: Term[OnChannel], inputs: Block,
               raw: np.ndarray, dv: np.ndarray | None) -> np.ndarray:
        x = _column(inputs, term.params.channel) - term.reference
        out: np.ndarray = x * x
        return out

    def one(self, term: Term[OnChannel], tracker: Any, raw: float, dv: float, inputs: Sample) -> float:
        x = float(inputs[term.params.channel]) - term.reference
        return x * x

    def code(self, term: Term[OnChannel], names: CodeNames) -> list[str]:
        return [f"    x = ({names.value} - {term.reference!r})", f"    shift += {term.coefficient!r} * "
                + ("(x * x * dv)" if term.form == "scale" else "(x * x)")]

    def kept_x(self, term: Term[OnChannel], value: str) -> str:
        x = f"({value} - {term.reference!r})"
        return f"({x} * {x})"  # the reference's x * x, x computed twice the same way

    def label(self, channel: str, tau_s: float | None = None) -> str:
        return f"({channel})²"

    def reach(self, term: Term[OnChannel], inputs: float) -> float:
        x = inputs + abs(term.reference)
        return x * x  # a float product overflows to inf (refused as not finite); ** would raise


class ChannelLagged(ChannelKind[L], SharedCode[L]):
    """The channel seen through a first-order lag y (:class:`ChannelTracker`); reads time too."""

    tracker_type = ChannelTracker
    derivative: ClassVar[bool] = False

    def input_names(self, term: Term[L]) -> tuple[str, ...]:
        return (term.params.channel, TIME_INPUT)

    def tracker(self, term: Term[L]) -> ChannelTracker:
        return ChannelTracker(term.params.tau_s, term.reference, self.derivative)

    def values(self, term: Term[L], inputs: Block, raw: np.ndarray, dv: np.ndarray | None) -> np.ndarray:
        return self.values_from(term, self.tracker(term), inputs, raw, dv)

    def values_from(self, term: Term[L], tracker: Any, inputs: Block, raw: np.ndarray,
                    dv: np.ndarray | None) -> np.ndarray:
        values = _column(inputs, term.params.channel)
        time_s = np.asarray(inputs[TIME_INPUT], dtype=float)
        return np.array([tracker.update(v, t) for v, t in zip(values.tolist(), time_s.tolist(), strict=True)],
                        dtype=float)

    def one(self, term: Term[L], tracker: Any, raw: float, dv: float, inputs: Sample) -> float:
        x: float = tracker.update(float(inputs[term.params.channel]), float(inputs[TIME_INPUT]))
        return x

    def code_x(self, term: Term[L], names: CodeNames) -> str:
        return f"{names.track}(float({names.value}), float({names.time}))"

    def describe(self, term: Term[L]) -> str:
        return self.label(term.params.channel, term.params.tau_s)


class ChannelLag(ChannelLagged[Lag]):
    """x = y − ref: the die feels the channel late."""

    feature = "lag"
    c_name = "CE_TERM_CHANNEL_LAG"
    record = Lag

    def label(self, channel: str, tau_s: float | None = None) -> str:
        return f"lag({channel}, τ={tau_s:.0f} s)" if tau_s else f"lag({channel})"


class ChannelDerivative(ChannelLagged[Lag]):
    """x = (v − y)/τ: the channel's rate of change smoothed with τ (a thermal transient)."""

    feature = "derivative"
    c_name = "CE_TERM_CHANNEL_DERIVATIVE"
    record = Lag
    derivative = True

    def label(self, channel: str, tau_s: float | None = None) -> str:
        return f"d/dt {channel}"

    def reach(self, term: Term[Lag], inputs: float) -> float:
        return 2.0 * inputs / term.params.tau_s  # |v − y| / τ, y a mean of past v


class ChannelDirection(ChannelKind[Gated], SharedCode[Gated]):
    """x = ±1: the sign of the channel's last change larger than ``threshold_raw`` (its units)."""

    feature = "direction"
    c_name = "CE_TERM_CHANNEL_DIRECTION"
    record = Gated
    tracker_type = DirectionTracker

    def tracker(self, term: Term[Gated]) -> DirectionTracker:
        return DirectionTracker(term.params.threshold_raw)

    def values(self, term: Term[Gated], inputs: Block, raw: np.ndarray, dv: np.ndarray | None) -> np.ndarray:
        return direction_state(_column(inputs, term.params.channel), term.params.threshold_raw)

    def values_from(self, term: Term[Gated], tracker: Any, inputs: Block, raw: np.ndarray,
                    dv: np.ndarray | None) -> np.ndarray:
        return direction_state(_column(inputs, term.params.channel), term.params.threshold_raw, tracker)

    def one(self, term: Term[Gated], tracker: Any, raw: float, dv: float, inputs: Sample) -> float:
        x: float = tracker.update(float(inputs[term.params.channel]))
        return x

    def code_x(self, term: Term[Gated], names: CodeNames) -> str:
        return f"{names.track}(float({names.value}))"

    def label(self, channel: str, tau_s: float | None = None) -> str:
        return f"sign d/dt {channel}"

    def reach(self, term: Term[Gated], inputs: float) -> float:
        return 1.0


class ChannelGated(ChannelKind[Gated]):
    """x = (v − ref)·g(ΔV) with the knee k = ``threshold_raw`` (raw units): an effect beyond a rate."""

    feature = "gated"
    c_name = "CE_TERM_CHANNEL_GATED"
    record = Gated

    def values(self, term: Term[Gated], inputs: Block, raw: np.ndarray, dv: np.ndarray | None) -> np.ndarray:
        if dv is None:
            raise ValueError("a gated term needs ΔV = raw − V0")
        return _offset_times(term, inputs, rate_gate(dv, term.params.threshold_raw))

    def one(self, term: Term[Gated], tracker: Any, raw: float, dv: float, inputs: Sample) -> float:
        return (float(inputs[term.params.channel]) - term.reference) * gate_one(dv, term.params.threshold_raw)

    def code(self, term: Term[Gated], names: CodeNames) -> list[str]:
        """:func:`~canical.sets.trackers.gate_one` written out: ``max(a, b)`` is ``b if b > a else a``."""
        k = term.params.threshold_raw
        return ["    a = abs(dv)", f"    g = a - {k!r}", "    g = 0.0 if 0.0 > g else g",
                f"    x = ({names.value} - {term.reference!r}) * (g / ({k!r} if {k!r} > a else a))",
                f"    shift += {term.coefficient!r} * " + ("(x * dv)" if term.form == "scale" else "x")]

    def describe(self, term: Term[Gated]) -> str:
        return f"{term.params.channel} × (|ΔV| > {term.params.threshold_raw:.0f} counts)"

    def label(self, channel: str, tau_s: float | None = None) -> str:
        return gated_name(channel)


#: Most knots a spline term may have (segments: one fewer): bounds the work per sample.
MAX_SPLINE_KNOTS = 64


def spline_one(knots: tuple[float, ...], pieces: tuple[tuple[float, ...], ...], v: float) -> float:
    """S(v) for one sample: v clamped to the knots' span, the segment by ``bisect``, Horner in
    u = v − knot. The block form (:func:`spline_values`) runs the same operations in the same order."""
    last = len(pieces) - 1
    w = knots[0] if v < knots[0] else knots[-1] if v > knots[-1] else v
    i = bisect_right(knots, w) - 1
    i = 0 if i < 0 else last if i > last else i
    a0, a1, a2, a3 = pieces[i]
    u = w - knots[i]
    return ((a3 * u + a2) * u + a1) * u + a0


def spline_values(knots: tuple[float, ...], pieces: tuple[tuple[float, ...], ...],
                  v: np.ndarray) -> np.ndarray:
    """S(v) for a block of samples, element by element what :func:`spline_one` gives."""
    return spline_horner(pieces, *spline_segments(knots, v))


def spline_segments(knots: tuple[float, ...], v: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The first half of :func:`spline_values`: each value's segment i and u = w − knot i, which
    every spline on these knots shares (the closed loop keeps them for a basis of many splines)."""
    k = np.asarray(knots, dtype=float)
    w = np.where(v < k[0], k[0], np.where(v > k[-1], k[-1], v))
    i = np.clip(np.searchsorted(k, w, side="right") - 1, 0, len(knots) - 2)
    return i, w - k[i]


def spline_horner(pieces: tuple[tuple[float, ...], ...], i: np.ndarray, u: np.ndarray) -> np.ndarray:
    """The second half of :func:`spline_values`: the cubic of segment i at u."""
    a = np.asarray(pieces, dtype=float)
    out: np.ndarray = ((a[i, 3] * u + a[i, 2]) * u + a[i, 1]) * u + a[i, 0]
    return out


class ChannelSpline(ChannelKind[Spline]):
    """x = S(v): a piecewise cubic of the channel learned from the data (a smooth effect whose
    form is on no list), flat beyond its end knots so a channel outside the calibrated range
    extrapolates nothing. ``knots`` b₀ < … < b_m, ``pieces`` m rows (a₀, a₁, a₂, a₃): on
    [b_i, b_i+1], S = a₀ + a₁u + a₂u² + a₃u³ with u = v − b_i. Bounded work per sample: one
    ``bisect`` and a cubic (in the C evaluator a binary search over the knots and the same
    cubic, in float32). Scale form: c·S(v)·ΔV, a nonlinearity changing with the channel.
    """

    feature = "spline"
    c_name = "CE_TERM_CHANNEL_SPLINE"
    record = Spline

    def values(self, term: Term[Spline], inputs: Block, raw: np.ndarray, dv: np.ndarray | None) -> np.ndarray:
        return spline_values(term.params.knots, term.params.pieces, _column(inputs, term.params.channel))

    def one(self, term: Term[Spline], tracker: Any, raw: float, dv: float, inputs: Sample) -> float:
        return spline_one(term.params.knots, term.params.pieces, float(inputs[term.params.channel]))

    def code(self, term: Term[Spline], names: CodeNames) -> list[str]:
        return [*spline_code(term.params, f"float({names.value})"),
                f"    shift += {term.coefficient!r} * " + ("(x * dv)" if term.form == "scale" else "x")]

    def label(self, channel: str, tau_s: float | None = None) -> str:
        return f"smooth({channel})"

    def reach(self, term: Term[Spline], inputs: float) -> float:
        return spline_reach(term.params)


def spline_code(curve: Curve, variable: str) -> list[str]:
    """:func:`spline_one` of the expression ``variable`` written out as statements leaving S in
    ``x``, the term's knots and pieces as constants."""
    knots, pieces, last = curve.knots, curve.pieces, len(curve.pieces) - 1
    lo, hi = knots[0], knots[-1]
    return [f"    w = {variable}",
            f"    w = {lo!r} if w < {lo!r} else {hi!r} if w > {hi!r} else w",
            f"    i = bisect_right({knots!r}, w) - 1",
            f"    i = 0 if i < 0 else {last} if i > {last} else i",
            f"    a0, a1, a2, a3 = {pieces!r}[i]",
            f"    u = w - {knots!r}[i]",
            "    x = ((a3 * u + a2) * u + a1) * u + a0"]


def spline_reach(curve: Curve) -> float:
    """The largest |S|: Σ|a_j|·h^j of the largest segment (S is flat beyond the knots)."""
    knots, pieces = curve.knots, curve.pieces
    return max((_poly_bound(row, b - k) for k, b, row in zip(knots[:-1], knots[1:], pieces, strict=True)),
               default=0.0)


def _poly_bound(row: tuple[float, ...], h: float) -> float:
    """Σ|a_j|·h^j by products, which overflow to inf (refused as not finite) where ** raises."""
    total, power = 0.0, 1.0
    for a in row:
        total += abs(a) * power if a else 0.0  # 0·inf would be nan
        power *= h
    return total


class ChannelRateSpline(ChannelKind[Spline]):
    """x = (v − ref)·R(ΔV): a channel's coefficient that changes smoothly with rate (a scale-factor
    temperature coefficient that depends on rate: the nonlinearity's shape changes with the
    channel). R is a piecewise cubic of ΔV = raw − V0 in raw units with the same ``knots`` and
    ``pieces`` as :class:`ChannelSpline`, flat beyond its end knots. Bias form c·x covers a
    coefficient of any smooth shape in rate (R holds its own ΔV factor where the data want one);
    scale form c·x·ΔV. Stateless: one lookup and a cubic per sample, like the gated level. The C
    evaluator runs R with the spline's own steps (``spline_at`` of the raw output, its knots held
    in raw counts as b + V0), then (v − ref)·R in float32.
    """

    feature = "rate_spline"
    c_name = "CE_TERM_CHANNEL_RATE_SPLINE"
    record = Spline

    def values(self, term: Term[Spline], inputs: Block, raw: np.ndarray, dv: np.ndarray | None) -> np.ndarray:
        if dv is None:
            raise ValueError("a rate_spline term needs ΔV = raw − V0")
        return _offset_times(term, inputs, spline_values(term.params.knots, term.params.pieces,
                                                         np.asarray(dv, dtype=float)))

    def one(self, term: Term[Spline], tracker: Any, raw: float, dv: float, inputs: Sample) -> float:
        offset = float(inputs[term.params.channel]) - term.reference
        return offset * spline_one(term.params.knots, term.params.pieces, dv)

    def code(self, term: Term[Spline], names: CodeNames) -> list[str]:
        return [*spline_code(term.params, "dv"), f"    x = ({names.value} - {term.reference!r}) * x",
                f"    shift += {term.coefficient!r} * " + ("(x * dv)" if term.form == "scale" else "x")]

    def describe(self, term: Term[Spline]) -> str:
        return self.label(term.params.channel)

    def label(self, channel: str, tau_s: float | None = None) -> str:
        return f"smooth({channel} × rate)"

    def reach(self, term: Term[Spline], inputs: float) -> float:
        return (inputs + abs(term.reference)) * spline_reach(term.params)


class ChannelTransformSpline(ChannelLagged[LagSpline]):
    """x = S(y): a piecewise cubic (as :class:`ChannelSpline`: ``knots``, ``pieces``, flat beyond
    the end knots) of one of the channel's lagged transforms, y its lagged level (``lag_spline``)
    or its rate of change smoothed over τ (``derivative_spline``): a smooth effect of what the die
    feels late, e.g. a bias saturating with a temperature that follows the chamber's with τ.
    The transform's state is the lag's :class:`ChannelTracker` with reference 0 (so y is the lag
    itself; ``reference`` plays no part), and S is :func:`spline_one` of its output: the same
    operations as the lag or derivative kind, then those of the spline kind. The C evaluator runs
    the lag's steps, then ``spline_at`` of y.
    """


    def tracker(self, term: Term[LagSpline]) -> ChannelTracker:
        return ChannelTracker(term.params.tau_s, 0.0, self.derivative)

    def values_from(self, term: Term[LagSpline], tracker: Any, inputs: Block, raw: np.ndarray,
                    dv: np.ndarray | None) -> np.ndarray:
        y = super().values_from(term, tracker, inputs, raw, dv)
        return spline_values(term.params.knots, term.params.pieces, y)

    def one(self, term: Term[LagSpline], tracker: Any, raw: float, dv: float, inputs: Sample) -> float:
        return spline_one(term.params.knots, term.params.pieces, super().one(term, tracker, raw, dv, inputs))

    def code(self, term: Term[LagSpline], names: CodeNames) -> list[str]:
        return [*spline_code(term.params, super().code_x(term, names)),
                f"    shift += {term.coefficient!r} * " + ("(x * dv)" if term.form == "scale" else "x")]

    def reach(self, term: Term[LagSpline], inputs: float) -> float:
        return spline_reach(term.params)


class ChannelLagSpline(ChannelTransformSpline):
    """x = S(y), y the channel through a first-order lag τ (:class:`ChannelLag` without its reference)."""

    feature = "lag_spline"
    c_name = "CE_TERM_CHANNEL_LAG_SPLINE"
    record = LagSpline

    def label(self, channel: str, tau_s: float | None = None) -> str:
        return f"smooth({CHANNEL_LAG.label(channel, tau_s)})"


class ChannelDerivativeSpline(ChannelTransformSpline):
    """x = S(d), d = (v − y)/τ the channel's rate of change smoothed with τ (:class:`ChannelDerivative`)."""

    feature = "derivative_spline"
    c_name = "CE_TERM_CHANNEL_DERIVATIVE_SPLINE"
    record = LagSpline
    derivative = True

    def label(self, channel: str, tau_s: float | None = None) -> str:
        return f"smooth({CHANNEL_DERIVATIVE.label(channel, tau_s)})"


def gated_name(channel: str, knee_dps: float | None = None) -> str:
    """``temp_c × (|rate| > 30 dps)``; without a knee, the candidate's name (knee to be estimated)."""
    knee = "knee" if knee_dps is None else f"{knee_dps:.0f} dps"
    return f"{channel} × (|rate| > {knee})"


class TimeKind(SharedCode[P]):
    """A function of time since power-on t (input ``time_s``); every one is kept between frames."""

    kind = TIME

    def input_names(self, term: Term[P]) -> tuple[str, ...]:
        return (TIME_INPUT,)


class TimeWarmup(TimeKind[Tau]):
    """x = 1 − exp(−t/τ)."""

    feature = "warmup"
    c_name = "CE_TERM_TIME_WARMUP"
    record = Tau

    def values(self, term: Term[Tau], inputs: Block, raw: np.ndarray, dv: np.ndarray | None) -> np.ndarray:
        warm: np.ndarray = 1.0 - np.exp(-_column(inputs, TIME_INPUT) / term.params.tau_s)
        return warm

    def one(self, term: Term[Tau], tracker: Any, raw: float, dv: float, inputs: Sample) -> float:
        return 1.0 - math.exp(-float(inputs[TIME_INPUT]) / (term.params.tau_s))

    def code_x(self, term: Term[Tau], names: CodeNames) -> str:
        return self.kept_x(term, names.value)

    def kept_x(self, term: Term[Tau], value: str) -> str:
        return f"(1.0 - exp(-{value} / {term.params.tau_s!r}))"

    def describe(self, term: Term[Tau]) -> str:
        return f"warm-up (τ={term.params.tau_s:.0f} s)"


class TimeLinear(TimeKind[NoParams]):
    """x = t: a linear drift."""

    feature = "linear"
    c_name = "CE_TERM_TIME_LINEAR"
    record = NoParams

    def values(self, term: Term[NoParams], inputs: Block,
               raw: np.ndarray, dv: np.ndarray | None) -> np.ndarray:
        return _column(inputs, TIME_INPUT)

    def one(self, term: Term[NoParams], tracker: Any, raw: float, dv: float, inputs: Sample) -> float:
        return float(inputs[TIME_INPUT])

    def code_x(self, term: Term[NoParams], names: CodeNames) -> str:
        return names.value

    def kept_x(self, term: Term[NoParams], value: str) -> str:
        return value

    def describe(self, term: Term[NoParams]) -> str:
        return "linear drift"

    def reach(self, term: Term[NoParams], inputs: float) -> float:
        return inputs


class DirectionSign(SharedCode[Threshold]):
    """x = ±1 (0 before either): the direction of the raw output's last significant change."""

    kind = DIRECTION
    feature = "sign"
    c_name = "CE_TERM_DIRECTION_SIGN"
    record = Threshold
    reads_raw = True
    tracker_type = DirectionTracker

    def tracker(self, term: Term[Threshold]) -> DirectionTracker:
        return DirectionTracker(term.params.threshold_raw)

    def values(self, term: Term[Threshold], inputs: Block,
               raw: np.ndarray, dv: np.ndarray | None) -> np.ndarray:
        return direction_state(raw, term.params.threshold_raw)

    def values_from(self, term: Term[Threshold], tracker: Any, inputs: Block, raw: np.ndarray,
                    dv: np.ndarray | None) -> np.ndarray:
        return direction_state(raw, term.params.threshold_raw, tracker)

    def one(self, term: Term[Threshold], tracker: Any, raw: float, dv: float, inputs: Sample) -> float:
        x: float = tracker.update(raw)
        return x

    def code_x(self, term: Term[Threshold], names: CodeNames) -> str:
        return f"{names.track}({names.raw})"

    def describe(self, term: Term[Threshold]) -> str:
        return "direction of approach"


class DirectionSlope(SharedCode[Tau]):
    """x = d(raw)/dt smoothed with τ (raw units per second; input ``time_s``)."""

    kind = DIRECTION
    feature = "slope"
    c_name = "CE_TERM_DIRECTION_SLOPE"
    record = Tau
    reads_raw = True
    tracker_type = SlopeTracker

    def input_names(self, term: Term[Tau]) -> tuple[str, ...]:
        return (TIME_INPUT,)

    def tracker(self, term: Term[Tau]) -> SlopeTracker:
        return SlopeTracker(term.params.tau_s)

    def values(self, term: Term[Tau], inputs: Block, raw: np.ndarray, dv: np.ndarray | None) -> np.ndarray:
        return slope_state(raw, np.asarray(inputs[TIME_INPUT], dtype=float), term.params.tau_s)

    def values_from(self, term: Term[Tau], tracker: Any, inputs: Block, raw: np.ndarray,
                    dv: np.ndarray | None) -> np.ndarray:
        return slope_state(raw, np.asarray(inputs[TIME_INPUT], dtype=float), term.params.tau_s, tracker)

    def one(self, term: Term[Tau], tracker: Any, raw: float, dv: float, inputs: Sample) -> float:
        x: float = tracker.update(raw, float(inputs[TIME_INPUT]))
        return x

    def code_x(self, term: Term[Tau], names: CodeNames) -> str:
        return f"{names.track}({names.raw}, float({names.time}))"

    def describe(self, term: Term[Tau]) -> str:
        return "rate of change of raw"

    def reach(self, term: Term[Tau], inputs: float) -> float:
        return inputs


CHANNEL_OFFSET = ChannelOffset()
CHANNEL_SQUARE = ChannelSquare()
CHANNEL_LAG = ChannelLag()
CHANNEL_DERIVATIVE = ChannelDerivative()
CHANNEL_DIRECTION = ChannelDirection()
CHANNEL_GATED = ChannelGated()
CHANNEL_SPLINE = ChannelSpline()
CHANNEL_RATE_SPLINE = ChannelRateSpline()
CHANNEL_LAG_SPLINE = ChannelLagSpline()
CHANNEL_DERIVATIVE_SPLINE = ChannelDerivativeSpline()
TIME_WARMUP = TimeWarmup()
TIME_LINEAR = TimeLinear()
DIRECTION_SIGN = DirectionSign()
DIRECTION_SLOPE = DirectionSlope()

#: Every kind this canical version reads, in the order error messages list them.
ALL: tuple[TermKind[Any], ...] = (CHANNEL_OFFSET, CHANNEL_SQUARE, CHANNEL_LAG, CHANNEL_DERIVATIVE,
                             CHANNEL_DIRECTION, CHANNEL_GATED, CHANNEL_SPLINE, CHANNEL_RATE_SPLINE,
                             CHANNEL_LAG_SPLINE, CHANNEL_DERIVATIVE_SPLINE, TIME_WARMUP, TIME_LINEAR,
                             DIRECTION_SIGN, DIRECTION_SLOPE)
_BY_KEY: dict[tuple[object, object], TermKind[Any]] = {k.key: k for k in ALL}
#: The features of each kind, as the set file names them.
FEATURES: dict[str, tuple[str, ...]] = {}
for _k in ALL:
    FEATURES.setdefault(_k.kind, ())
    FEATURES[_k.kind] += (_k.feature,)


def host_only(terms: tuple[Term, ...]) -> str | None:
    """The first of a set's terms the C evaluator refuses, as ``terms[i] (kind/feature)`` (None:
    the device evaluates them all). Why: a device would refuse the bank (``CE_ERR_TERM_KIND``)
    after the download; ``canical push`` says so before sending anything."""
    for i, t in enumerate(terms):
        spec = t.spec
        if spec.c_name is None:
            return f"terms[{i}] ({spec.kind}/{spec.feature})"
    return None


def registered(kind: str, feature: str) -> TermKind[Any]:
    """The registry's object for a kind it holds (KeyError: none; an unpickled term names one)."""
    return _BY_KEY[(kind, feature)]


def lookup(kind: object, feature: object) -> TermKind[Any] | None:
    """The kind a set file's ``kind``/``feature`` pair names (None: not one this version reads)."""
    return _BY_KEY.get((kind, feature))
