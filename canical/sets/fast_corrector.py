"""One axis's correction as straight-line scalar code, generated when its set is loaded.

Why: :meth:`Corrector.correct_one <canical.sets.corrector.Corrector.correct_one>` is general — it
walks its terms, asks each what it is, loops over knots and coefficients — and that costs
more per frame than everything else the daemon does. A set never changes while it is in use,
so its correction is written out once as Python source with every number a constant: the
terms one line each, the segment found by ``bisect``, the polynomial in Horner form unrolled.

It must give exactly what ``correct_one`` gives (the tests compare bit for bit on random sets
and inputs), so every floating-point operation is the reference's, in the reference's order.
The stateful terms (direction and slope of the raw output; lag, derivative and direction of a
channel) keep their state in the corrector's own tracker objects, called with the reference's
arguments, so the compiled function and ``correct_one`` share one stream: either may take the
next sample, and a function compiled again from the same corrector (a reload that keeps the
set) carries on where the last left off. A term kind or model this module does
not know is not compiled: :func:`compile_corrector` returns None and the caller keeps the
reference path, which stays the definition.
"""

from __future__ import annotations

import math
from bisect import bisect_right
from collections.abc import Callable, Mapping
from itertools import pairwise
from typing import Any

from canical.models.piecewise import PiecewisePoly
from canical.sets.corrector import Corrector
from canical.sets.term_kinds import ALL, TIME_INPUT, CodeNames, KeptCode, TermCode
from canical.sets.terms import Term

#: ``(raw, inputs) -> (rate, out_of_span)``, as ``Corrector.correct_one``.
CorrectOne = Callable[[float, Mapping[str, float]], tuple[float, bool]]

#: The (kind, feature) pairs compiled here: every kind of the registry writes its own statements.
COMPILED_TERMS = {k.key for k in ALL}


def why_not(corrector: Corrector) -> str | None:
    """Why this corrector is not compiled (None: it is)."""
    for term, tracker in zip(corrector.terms, corrector.trackers, strict=True):
        spec = term.spec
        if spec.key not in COMPILED_TERMS:
            return f"term {term.kind}/{term.feature} not compiled"
        expected = spec.tracker_type or type(None)
        if type(tracker) is not expected:
            return f"term {term.kind}/{term.feature} has state {type(tracker).__name__}"
    model = corrector.model
    if isinstance(model, PiecewisePoly):
        knots = model.knots_list
        if any(not b >= a for a, b in pairwise(knots)):  # bisect needs them sorted
            return "segment points not in ascending order"
    return None


def _term_lines(j: int, term: Term, raw: str, inputs: Callable[[str], str], tag: str,
                cached: frozenset[str] = frozenset(), state: list[str] | None = None) -> list[str]:
    """The reference's feature x and its share of the shift, for term ``j``.

    The reference converts an input with ``float()`` first; every use below combines it with
    a float (``v - ref``, ``-v / tau``, ``c * v``), which converts an int the same way, so the
    call is left out. Trackers get exactly the reference's arguments. Each kind writes its own
    statements (:meth:`~canical.sets.term_kinds.TermCode.code`).

    A stateless term whose input is a name in ``cached`` (an input that changes only when
    its own frame arrives, not every raw frame) keeps the part that depends on the input
    alone between calls: recomputed, by the same expression, only when the input is another
    object than last time (:func:`_cache_lines`); ``state`` collects the names that keep it.
    """
    spec: TermCode = term.spec  # the code part of the kind's contract (and KeptCode, if kept)
    first = term.input_name
    value = inputs(first) if first is not None else ""
    scale = term.form == "scale"
    if state is not None and value in cached and isinstance(spec, KeptCode):
        x = spec.kept_x(term, value)
        if scale and x == value:  # nothing but the input itself: nothing to keep
            return [f"    shift += {term.coefficient!r} * ({value} * dv)"]
        kept = x if scale else f"{term.coefficient!r} * {x}"
        lines, name = _cache_lines(value, kept, f"{tag}t{j}_", state)
        share = f"{term.coefficient!r} * ({name} * dv)" if scale else name
        return [*lines, f"    shift += {share}"]
    return spec.code(term, CodeNames(value, inputs(TIME_INPUT), raw, f"{tag}track{j}"))


def _cache_lines(value: str, expr: str, prefix: str, state: list[str]) -> tuple[list[str], str]:
    """``expr`` (of the input ``value`` alone) kept in ``prefix + "v"``, recomputed only when
    ``value`` is not the object it was computed from. The key is set after the value, so an
    exception (as the reference would raise, at the same point) leaves nothing half kept."""
    key, kept = f"{prefix}k", f"{prefix}v"
    state += [key, kept]
    return [f"    if {value} is not {key}:", f"        {kept} = {expr}", f"        {key} = {value}"], kept


def with_state(header: str, body: list[str], state: list[str], name: str) -> list[str]:
    """Source of a factory ``make()`` returning the function ``header`` + ``body``, whose kept
    values (``state``, from :func:`corrector_lines`) live in the factory's closure: read and
    written as fast as locals, fresh (a key no input is) for each function made."""
    if not state:
        return ["def make():", *(f"    {line}" for line in [header, *body]), f"    return {name}"]
    return ["def make():", f"    {' = '.join(state)} = NOTHING", f"    {header}",
            f"        nonlocal {', '.join(state)}", *(f"    {line}" for line in body), f"    return {name}"]


#: Most segments whose lookup is written out as a tree of comparisons (more: ``bisect``).
MAX_TREE_SEGMENTS = 16


def _foldable(model: PiecewisePoly) -> bool:
    """Whether the coefficients and segment points can be written into the source as literals (finite floats:
    ``repr`` gives them back exactly; ``inf``/``nan`` have no literal)."""
    return (len(model.coeffs_list) <= MAX_TREE_SEGMENTS
            and all(type(c) is float and math.isfinite(c) for row in model.coeffs_list for c in row)
            and all(type(k) is float and math.isfinite(k) for k in model.knots_list))


def _segment_tree(knots: list[float], rows: list[list[float]], a: int, b: int, depth: int,
                  x: str = "x") -> list[str]:
    """Segments ``a..b-1`` as nested comparisons, each leaf the Horner line with its segment's
    coefficients as constants. Segment ``i`` is ``knots[i-1] <= x < knots[i]``: the reference's
    segment (the first knot ``x`` is below), for sorted knots the same as ``bisect_right``."""
    pad = "    " * depth
    if b - a == 1:
        c = [f"({v!r})" for v in rows[a]]
        horner = c[-1]
        for k in range(len(c) - 2, -1, -1):
            horner = f"({horner}) * u + {c[k]}"
        return [f"{pad}acc = {horner}"]
    mid = (a + b) // 2
    return [f"{pad}if {x} < {knots[mid - 1]!r}:", *_segment_tree(knots, rows, a, mid, depth + 1, x),
            f"{pad}else:", *_segment_tree(knots, rows, mid, b, depth + 1, x)]


def _model_lines(model: PiecewisePoly, dv: str, tag: str, rate: str, out: str) -> list[str]:
    """:meth:`PiecewisePoly.evaluate_one`, unrolled for this set's order, into ``rate, out``.

    Where the coefficients fold (:func:`_foldable`), the segment is found by a tree of
    comparisons with the segment points as constants and each segment's Horner line has its
    coefficients written in: no ``bisect`` call, no tuple to index and unpack. Beyond the span
    the reference evaluates at the span's end and extrapolates by the slope there: both ends'
    value and slope over scale are the same every time, so they are computed once, here, by
    the very statements the general form runs, and written in as constants. The same
    operations in the same order, so the same bits; a NaN goes the general way.
    """
    lo, hi = model.span
    if not _foldable(model):
        return _general_model_lines(model, dv, tag, rate, out)
    unpack, horner, slope = _model_parts(model, tag)
    namespace: dict[str, Any] = {"bisect_right": bisect_right, f"{tag}KNOTS": tuple(model.knots_list),
                                 f"{tag}COEFFS": tuple(tuple(row) for row in model.coeffs_list)}
    # The general statements on x, the span's end (where the reference clips to), as they run
    # beyond the span: the row, u, Horner, the slope, the slope over the scale.
    source = "\n".join(["def edge(x):", f"    {unpack}", f"    u = x / {model.scale!r}",
                        f"    acc = {horner}", *(line[4:] for line in slope),
                        f"    return acc, slope / {model.scale!r}"]) + "\n"
    exec(compile(source, "<span end>", "exec"), namespace)
    (acc_lo, k_lo), (acc_hi, k_hi) = ends = namespace["edge"](lo), namespace["edge"](hi)
    if not all(type(v) is float and math.isfinite(v) for pair in ends for v in pair):
        return _general_model_lines(model, dv, tag, rate, out)
    rows = model.coeffs_list
    return [f"    if {dv} < {lo!r}:",
            f"        {rate}, {out} = {acc_lo!r} + ({k_lo!r}) * ({dv} - {lo!r}), True",
            f"    elif {dv} > {hi!r}:",
            f"        {rate}, {out} = {acc_hi!r} + ({k_hi!r}) * ({dv} - {hi!r}), True",
            f"    elif {dv} == {dv}:  # inside the span",
            f"        u = {dv} / {model.scale!r}",
            *(f"    {line}" for line in _segment_tree(model.knots_list, rows, 0, len(rows), 1, dv)),
            f"        {rate}, {out} = acc, False",
            "    else:  # NaN: the general statements, whatever they make of it",
            *(f"    {line}" for line in _general_model_lines(model, dv, tag, rate, out))]


def _model_parts(model: PiecewisePoly, tag: str) -> tuple[str, str, list[str]]:
    """The general form's row lookup (into ``c0, c1, …``), Horner in ``u`` and slope lines."""
    m = len(model.coeffs_list[0]) - 1
    horner = f"c{m}"
    for k in range(m - 1, -1, -1):
        horner = f"({horner}) * u + c{k}"
    slope = ["        slope = 0.0"] + [f"        slope = slope * u + {k} * c{k}" for k in range(m, 0, -1)]
    row = f"{tag}COEFFS[bisect_right({tag}KNOTS, x)]" if model.knots_list else f"{tag}COEFFS[0]"
    return f"{''.join(f'c{k}, ' for k in range(m + 1))}= {row}", horner, slope


def _general_model_lines(model: PiecewisePoly, dv: str, tag: str, rate: str, out: str) -> list[str]:
    """:meth:`PiecewisePoly.evaluate_one` for any coefficients: the row by ``bisect``, Horner
    and (beyond the span) the slope from it."""
    lo, hi = model.span
    unpack, horner, slope = _model_parts(model, tag)
    return [
        f"    x = {lo!r} if {dv} < {lo!r} else {hi!r} if {dv} > {hi!r} else {dv}",
        f"    {unpack}",
        f"    u = x / {model.scale!r}",
        f"    acc = {horner}",
        f"    if x == {dv}:",
        f"        {rate}, {out} = acc, False",
        "    else:",
        *slope,
        f"        {rate}, {out} = acc + slope / {model.scale!r} * ({dv} - x), True",
    ]


def corrector_lines(corrector: Corrector, raw: str, inputs: str, rate: str, out: str,
                    tag: str = "", held: Mapping[str, str] | None = None,
                    cached: frozenset[str] = frozenset(), state: list[str] | None = None,
                    ) -> tuple[list[str], dict[str, Any]]:
    """``rate, out = corrector.correct_one(raw, inputs)`` as straight-line statements (one level
    of indentation), and the names they need; for a corrector :func:`why_not` passes.

    ``raw`` and ``inputs`` are the expressions of the raw value (a local name) and the inputs'
    mapping; ``tag`` prefixes this corrector's constants, so several can share one function
    (the daemon writes a whole frame's three axes as one); ``held`` names local variables
    that already hold inputs (read once per frame, not once per term). Temporaries (``dv``,
    ``x``, ``u``, …) are overwritten. The statements share the corrector's tracker objects: build them after
    its last ``reset()``. With ``state`` (a list the names are added to), the terms whose
    input is one of the ``cached`` held names keep their input's part between frames: the
    statements must then go into a function made by :func:`with_state`.
    """
    terms = corrector.terms
    lines = []
    held = held or {}

    def value_of(name: str) -> str:
        return held.get(name, f"{inputs}[{name!r}]")

    if any(t.spec.reads_raw for t in terms):
        lines.append(f"    rawf = float({raw})")
        raw = "rawf"
    lines.append(f"    dv = {raw} - {corrector.v0!r}")
    namespace: dict[str, Any] = {"exp": math.exp, "bisect_right": bisect_right, "NOTHING": object()}
    if terms:
        lines.append("    shift = 0.0")
        for j, (term, tracker) in enumerate(zip(terms, corrector.trackers, strict=True)):
            if tracker is not None:
                namespace[f"{tag}track{j}"] = tracker.update
            lines += _term_lines(j, term, raw, value_of, tag, cached, state)
        lines.append("    d = dv - shift")
        dv = "d"
    else:
        dv = "dv"
    model = corrector.model
    if isinstance(model, PiecewisePoly):
        namespace[f"{tag}KNOTS"] = tuple(model.knots_list)
        namespace[f"{tag}COEFFS"] = tuple(tuple(row) for row in model.coeffs_list)
        lines += _model_lines(model, dv, tag, rate, out)
    else:  # a forward polynomial: Newton's method stays the model's own
        namespace[f"{tag}model_one"] = model.evaluate_one
        lines.append(f"    {rate}, {out} = {tag}model_one({dv})")
    return lines, namespace


def compile_corrector(corrector: Corrector) -> CorrectOne | None:
    """``corrector.correct_one`` as generated code, or None when something in it is not compiled.

    The function shares the corrector's tracker objects: build it after the last ``reset()``.
    """
    if why_not(corrector) is not None:
        return None
    body, namespace = corrector_lines(corrector, "raw", "inputs", "rate", "out")
    source = "\n".join(["def correct_one(raw, inputs):", *body, "    return rate, out"]) + "\n"
    exec(compile(source, f"<corrector {corrector.set_id:08x}>", "exec"), namespace)
    function = namespace["correct_one"]
    function.source = source
    return function  # type: ignore[no-any-return]
