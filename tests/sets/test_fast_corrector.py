"""The compiled per-axis correction against the reference, on random sets, terms and streams.

Bit for bit against ``Corrector.correct_one`` (same operations in the same order), every
term kind included, stateful ones (direction, slope; a channel's lag, derivative, direction)
over whole streams, also when the stream passes between the compiled function, a function
compiled again from the same corrector (a reload that keeps the set) and ``correct_one``;
against the block
path ``Corrector.correct`` exactly where no warm-up term is involved and within 1e-12
relative where one is (``numpy.exp`` and ``math.exp`` may differ in the last bit).
"""

from __future__ import annotations

import math
import struct

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from canical.models.kinds import SEGMENTED_INVERSE, SEGMENTED_LINEAR
from canical.sets.coefficients import CoefficientSet
from canical.sets.corrector import Corrector
from canical.sets.fast_corrector import (
    COMPILED_TERMS,
    compile_corrector,
    corrector_lines,
    why_not,
    with_state,
)
from canical.sets.set_model import PiecewiseModel, model_of
from canical.sets.term_kinds import ChannelLag, registered
from canical.sets.terms import STATEFUL_CHANNEL, Term, term_from_dict

INPUTS = ("temp_c", "supply_v")
finite = st.floats(-1e3, 1e3, allow_nan=False, allow_infinity=False)


def bits(x: float) -> bytes:
    return struct.pack("<d", x)


@st.composite
def terms(draw) -> dict:
    kind, feature = draw(st.sampled_from(sorted(COMPILED_TERMS)))
    term = {"kind": kind, "feature": feature, "form": draw(st.sampled_from(("bias", "scale"))),
            "coefficient": draw(st.floats(-0.5, 0.5, allow_nan=False)), "reference": None,
            "channel": None, "tau_s": None, "threshold_raw": None}
    if kind == "channel":
        term["channel"] = draw(st.sampled_from(INPUTS))
        term["reference"] = draw(finite)
    if registered(kind, feature).needs_tau:
        term["tau_s"] = draw(st.floats(0.01, 500.0))
    if feature in ("sign", "gated"):
        term["threshold_raw"] = draw(st.floats(0.5, 500.0))
    if kind == "channel" and feature == "direction":
        term["threshold_raw"] = draw(st.floats(0.01, 50.0))  # in the channel's own units
    if registered(kind, feature).needs_spline:
        knots = sorted(set(draw(st.lists(finite, min_size=2, max_size=7))))
        if len(knots) < 2:
            knots = [knots[0], knots[0] + 1.0]
        term["knots"] = knots
        term["pieces"] = [draw(st.lists(st.floats(-2.0, 2.0), min_size=4, max_size=4)) for _ in knots[1:]]
    return term


@st.composite
def piecewise_sets(draw) -> CoefficientSet:
    """A segmented set with random segment points, order, scale, span, coefficients and terms."""
    n_seg = draw(st.integers(1, 6))
    order = draw(st.integers(0, 4))
    v0 = draw(st.floats(-500.0, 500.0))
    lo = draw(st.floats(-30000.0, -100.0))
    hi = draw(st.floats(100.0, 30000.0))
    knots = sorted(set(draw(st.lists(st.floats(lo, hi), min_size=n_seg - 1, max_size=n_seg - 1))))
    coeffs = [[draw(st.floats(-500.0, 500.0)) for _ in range(order + 1)] for _ in range(len(knots) + 1)]
    # Built directly, not validated: the compiled corrector must follow the reference on any set.
    model = PiecewiseModel(SEGMENTED_INVERSE, tuple(k + v0 for k in knots),
                           draw(st.sampled_from((1, 1000.0, hi, 24365.85262086632))),
                           tuple(tuple(row) for row in coeffs), (lo + v0, hi + v0), None, ())
    drawn = draw(st.lists(terms(), max_size=5))
    return CoefficientSet("s", "x", v0, model, tuple(term_from_dict(t) for t in drawn))


@st.composite
def streams(draw) -> list[tuple[float, dict]]:
    """Samples in time order: raw (int or float, inside and beyond the span) and inputs."""
    n = draw(st.integers(1, 40))
    t = draw(st.floats(0.0, 1e4))
    out = []
    for _ in range(n):
        raw = draw(st.one_of(st.integers(-32768, 32767), st.floats(-40000.0, 40000.0)))
        t += draw(st.sampled_from((0.0, 0.005, 0.01, 1.0))) + draw(st.floats(0.0, 0.1))
        inputs = {name: draw(st.one_of(finite, st.integers(-100, 100))) for name in INPUTS}
        inputs["time_s"] = draw(st.sampled_from((t, round(t))))
        out.append((raw, inputs))
    return out


@settings(max_examples=500, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cset=piecewise_sets(), stream=streams())
def test_compiled_equals_reference_bit_for_bit(cset: CoefficientSet, stream) -> None:
    reference, other = Corrector(cset), Corrector(cset)
    compiled = compile_corrector(other)
    assert compiled is not None, why_not(other)
    for raw, inputs in stream:
        want, got = reference.correct_one(raw, inputs), compiled(raw, inputs)
        assert got[1] == want[1]
        assert bits(got[0]) == bits(want[0]) or (math.isnan(got[0]) and math.isnan(want[0])), (
            compiled.source, raw, inputs, got, want)  # type: ignore[attr-defined]


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cset=piecewise_sets())
def test_segment_points_and_span_ends_exactly(cset: CoefficientSet) -> None:
    """On each segment point and span end, one step either side of it, far beyond, and NaN:
    the comparison tree picks the reference's segment and the written-in ends extrapolate as
    the reference does (no terms, so the corrected value is exactly the point)."""
    import dataclasses

    model = cset.model
    assert isinstance(model, PiecewiseModel)
    v0 = cset.v0
    model = dataclasses.replace(model, knots_raw=tuple(k - v0 for k in model.knots_raw),
                                span_raw=(model.span_raw[0] - v0, model.span_raw[1] - v0))
    bare = dataclasses.replace(cset, v0=0.0, model=model, terms=())
    reference, compiled = Corrector(bare), compile_corrector(Corrector(bare))
    assert compiled is not None
    edges = [*reference.model._knots_list, *reference.model.span]
    points = [p for e in edges for p in (math.nextafter(e, -math.inf), e, math.nextafter(e, math.inf))]
    for raw in [*points, -1e9, 1e9, math.nan]:
        want, got = reference.correct_one(raw, {}), compiled(raw, {})
        assert got[1] == want[1], raw
        assert bits(got[0]) == bits(want[0]) or (math.isnan(got[0]) and math.isnan(want[0])), (raw, got, want)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cset=piecewise_sets(), stream=streams(), data=st.data())
def test_state_carries_across_functions_and_reloads(cset: CoefficientSet, stream, data) -> None:
    """One stream, each sample taken by the compiled function, by one compiled again from the
    same corrector (a reload that keeps the set) or by ``correct_one``: the state is the
    corrector's, so the rates are those of one reference corrector fed the whole stream."""
    reference, shared = Corrector(cset), Corrector(cset)
    functions = [compile_corrector(shared)]
    for raw, inputs in stream:
        how = data.draw(st.sampled_from(("compiled", "recompiled", "reference")))
        if how == "recompiled":
            functions.append(compile_corrector(shared))
        correct = shared.correct_one if how == "reference" else functions[-1]
        want, got = reference.correct_one(raw, inputs), correct(raw, inputs)  # type: ignore[misc]
        assert got[1] == want[1]
        assert bits(got[0]) == bits(want[0]) or (math.isnan(got[0]) and math.isnan(want[0])), (how, raw)


def kept_inputs_function(corrector: Corrector):
    """The corrector as the daemon writes it: every input read once into a local, and all of
    them other frames' (kept between calls while the same object)."""
    names = (*INPUTS, "time_s")
    held = {name: f"h{i}" for i, name in enumerate(names)}
    state: list[str] = []
    body, namespace = corrector_lines(corrector, "raw", "inputs", "rate", "out", held=held,
                                      cached=frozenset(held.values()), state=state)
    reads = [f"    {held[name]} = inputs[{name!r}]" for name in names]
    lines = with_state("def correct(raw, inputs):", [*reads, *body, "    return rate, out"], state, "correct")
    exec(compile("\n".join(lines) + "\n", "<kept>", "exec"), namespace)
    return namespace["make"](), state


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cset=piecewise_sets(), stream=streams(), data=st.data())
def test_kept_input_terms_equal_reference_bit_for_bit(cset: CoefficientSet, stream, data) -> None:
    """Terms of inputs that change only when their frame arrives, kept between frames: bit for
    bit the reference's, when the inputs stay the same objects for several frames (the kept
    value used) and when they change (recomputed), ints and floats alike."""
    reference, other = Corrector(cset), Corrector(cset)
    correct, state = kept_inputs_function(other)
    if any(t.feature in ("offset", "square", "warmup") for t in other.terms):
        assert state  # something is kept
    last: dict = {}
    for raw, fresh in stream:
        inputs = {name: last[name] if name in last and data.draw(st.booleans()) else value
                  for name, value in fresh.items()}
        last = inputs
        want, got = reference.correct_one(raw, inputs), correct(raw, inputs)
        assert got[1] == want[1]
        assert bits(got[0]) == bits(want[0]) or (math.isnan(got[0]) and math.isnan(want[0])), (raw, inputs)


@settings(max_examples=300, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(cset=piecewise_sets(), stream=streams())
def test_compiled_equals_the_block_path(cset: CoefficientSet, stream) -> None:
    corrector = Corrector(cset)
    compiled = compile_corrector(Corrector(cset))
    assert compiled is not None
    raw = np.array([float(r) for r, _ in stream])
    block_inputs = {name: np.array([float(i[name]) for _, i in stream]) for name in (*INPUTS, "time_s")}
    rate, out = corrector.correct(raw, block_inputs)
    one = [compiled(r, i) for r, i in stream]
    assert [o for _, o in one] == out.tolist()
    got = np.array([r for r, _ in one])
    if any(t.feature == "warmup" for t in corrector.terms):
        np.testing.assert_allclose(got, rate, rtol=1e-12, atol=1e-12)
    else:
        np.testing.assert_array_equal(got, rate)


def test_forward_polynomial_keeps_its_newton_solver() -> None:
    model = model_of({"kind": "forward-poly", "coefficients": [3.0, 1000.0, 20.0, -4.0], "rate_scale": 100.0,
                      "rate_span_dps": [-300.0, 300.0], "span_raw": [-2500.0, 2500.0],
                      "out_of_span": "linear-extrapolation"})
    term = {"kind": "channel", "channel": "temp_c", "feature": "offset", "form": "bias", "coefficient": 0.3,
            "reference": 20.0}
    cset = CoefficientSet("s", "x", 10.0, model, (term_from_dict(term),))
    reference = Corrector(cset)
    compiled = compile_corrector(Corrector(cset))
    assert compiled is not None
    for raw in range(-4000, 4000, 37):
        assert compiled(raw, {"temp_c": 31.5}) == reference.correct_one(raw, {"temp_c": 31.5})


def test_a_term_kind_it_does_not_know_is_left_to_the_reference() -> None:
    """A kind added later (here: a lagged channel) is not compiled; the caller keeps correct_one."""
    model = model_of({"kind": "segmented-linear", "knots_raw": [0.0], "segment_points_dps": [0.0],
                      "scale": 1000.0, "coefficients": [[0.0, 100.0], [0.0, 110.0]], "smoothness": 0,
                      "span_raw": [-900.0, 900.0], "out_of_span": "linear-extrapolation"})
    corrector = Corrector(CoefficientSet("s", "x", 0.0, model))
    assert compile_corrector(corrector) is not None
    class LaterKind(ChannelLag):  # a kind of a later version: not in this version's registry
        feature = "sample"

    corrector.terms = (Term.of(LaterKind(), "bias", 1.0, channel="temp_c", tau_s=1.0),)
    corrector._trackers = [None]
    assert why_not(corrector) == "term channel/sample not compiled"
    assert compile_corrector(corrector) is None


def test_unsorted_segment_points_are_left_to_the_reference() -> None:
    """bisect assumes sorted points, the reference's scan does not: such a set is not compiled."""
    # Built directly: a file with these points is refused at load; the corrector must not rely on that.
    model = PiecewiseModel(SEGMENTED_LINEAR, (50.0, -50.0), 1000.0, ((0.0, 100.0), (0.0, 110.0), (1.0, 90.0)),
                           (-900.0, 900.0), 0, (0.0, 0.0))
    corrector = Corrector(CoefficientSet("s", "x", 0.0, model))
    assert why_not(corrector) == "segment points not in ascending order"
    assert compile_corrector(corrector) is None


@pytest.mark.parametrize("feature", [*STATEFUL_CHANNEL, "gated"])
def test_channel_terms_with_state_or_gate_are_compiled(feature: str) -> None:
    """Lag, derivative and direction of a channel (state kept per stream) and the rate gate are
    compiled, beside a stateless term: the daemon no longer falls back to correct_one for them."""
    model = model_of({"kind": "segmented-linear", "knots_raw": [0.0], "segment_points_dps": [0.0],
                      "scale": 1000.0, "coefficients": [[0.0, 100.0], [0.0, 110.0]], "smoothness": 0,
                      "span_raw": [-900.0, 900.0], "out_of_span": "linear-extrapolation"})
    term = {"kind": "channel", "channel": "temp_c", "feature": feature, "form": "scale",
            "coefficient": 0.01, "reference": 25.0, "tau_s": 2.0, "threshold_raw": 0.5}
    if registered("channel", feature).needs_spline:  # of the lag, or of its rate
        knots = [20.0, 24.0, 31.0] if feature == "lag_spline" else [-0.3, 0.05, 0.3]
        term.update(knots=knots, pieces=[[0.5, -0.25, 0.125, -0.0625], [-0.3, 0.1, 0.05, -0.01]])
    offset = {"kind": "channel", "channel": "temp_c", "feature": "offset", "form": "bias", "coefficient": 0.1,
              "reference": 25.0}
    cset = CoefficientSet("s", "x", 0.0, model, (term_from_dict(offset), term_from_dict(term)))
    reference, corrector = Corrector(cset), Corrector(cset)
    assert why_not(corrector) is None
    compiled = compile_corrector(corrector)
    assert compiled is not None
    for i in range(200):  # heating then cooling, rates through the knee
        inputs = {"temp_c": 25.0 + 5.0 * math.sin(i / 30.0), "time_s": 0.1 * i}
        raw = 800.0 * math.sin(i / 7.0)
        assert compiled(raw, inputs) == reference.correct_one(raw, inputs)
