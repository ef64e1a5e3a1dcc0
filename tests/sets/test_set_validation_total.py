"""Validation is total: any mapping either loads as a set whose every output is finite, or is
refused in one line; never another exception.

Mappings are mutations of valid sets (a value replaced by something odd, a key dropped or
added, a list shortened or lengthened, a number scaled towards overflow) with the CRC
recomputed, so that what is exercised is the checks behind the CRC. A set that loads is run on
rows inside its span, at its ends and far beyond them (up to a 32-bit count away), with inputs
up to ±1e6, by the block path, the one-sample path and the compiled corrector.
"""

from __future__ import annotations

import contextlib
import copy
import math
import os
from typing import Any

import numpy as np
import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from canical.errors import CanicalError
from canical.sets import coefficient_file
from canical.sets.coefficient_file import content_crc, loads
from canical.sets.coefficients import CoefficientSet
from canical.sets.corrector import Corrector
from canical.sets.fast_corrector import compile_corrector
from canical.sets.set_model import model_of
from canical.sets.term_kinds import ALL
from canical.sets.terms import term_from_dict

PIECEWISE = {"kind": "segmented-inverse", "knots_raw": [-8000.0, 8000.0], "segment_points_dps": [-20.0, 20.0],
             "scale": 20000.0, "coefficients": [[0.5, 52.0, 0.4, 0.1], [0.0, 50.0, 0.2, -0.3],
                                                [-0.5, 52.0, -0.4, 0.1]],
             "smoothness": 0, "span_raw": [-24000.0, 24000.0], "out_of_span": "linear-extrapolation"}
FORWARD = {"kind": "forward-poly", "coefficients": [3.0, 24000.0, 15.0, 120.0], "rate_scale": 60.0,
           "rate_span_dps": [-60.0, 60.0], "span_raw": [-24000.0, 24000.0],
           "out_of_span": "linear-extrapolation"}


def _term(kind: Any) -> dict[str, Any]:
    d: dict[str, Any] = {"kind": kind.kind, "feature": kind.feature, "form": "bias", "coefficient": 1.5e-3}
    if kind.needs_channel:
        d["channel"] = "temp_c"
        d["reference"] = 25.0
    if kind.needs_tau:
        d["tau_s"] = 30.0
    if kind.needs_threshold:
        d["threshold_raw"] = 0.5 if kind.needs_channel else 300.0
    if kind.needs_spline:
        d["knots"] = [10.0, 25.0, 40.0]
        d["pieces"] = [[0.0, 0.5, -0.01, 1e-4], [2.0, 0.1, 0.02, -2e-4]]
    return d


def _content(model: dict[str, Any], terms: tuple[dict[str, Any], ...]) -> dict[str, Any]:
    typed = tuple(term_from_dict(t) for t in terms)
    text = coefficient_file.dumps(CoefficientSet("S1", "z", 12.0, model_of(model), typed, {"rms_dps": 0.01},
                                                 "2026"))
    content: dict[str, Any] = yaml.safe_load(text)
    return content


BASES = (
    _content(PIECEWISE, ()),
    _content(PIECEWISE, tuple(_term(k) for k in ALL)),
    _content(FORWARD, ()),
)

odd_numbers = st.sampled_from([1e308, -1e308, 1e300, 1e150, 1e-308, 5e-324, 0.0, -0.0, 2**64, -(2**70),
                               float("inf"), float("nan"), 1, -1, True])
odd_values = st.one_of(
    st.none(), st.booleans(), odd_numbers,
    st.floats(allow_nan=True, allow_infinity=True), st.integers(-(2**80), 2**80),
    st.text(max_size=4), st.sampled_from(["channel", "time", "direction", "gated", "lag", "scale", "bias"]),
    st.lists(st.floats(-1e3, 1e3), max_size=4),
    st.lists(st.lists(st.floats(-1e3, 1e3), max_size=3), max_size=3),
    st.dictionaries(st.text(max_size=3), st.integers(), max_size=2),
)


def _paths(node: Any, path: tuple[Any, ...] = ()) -> list[tuple[Any, ...]]:
    out = [path]
    if isinstance(node, dict):
        for k, v in node.items():
            if k != "crc32":
                out += _paths(v, (*path, k))
    elif isinstance(node, list):
        for i, v in enumerate(node):
            out += _paths(v, (*path, i))
    return out


def _get(node: Any, path: tuple[Any, ...]) -> Any:
    for key in path:
        node = node[key]
    return node


@st.composite
def mutated(draw: st.DrawFn) -> dict[str, Any]:
    content = copy.deepcopy(draw(st.sampled_from(BASES)))
    for _ in range(draw(st.integers(1, 3))):
        path = draw(st.sampled_from(_paths(content)[1:]))
        parent, key = _get(content, path[:-1]), path[-1]
        action = draw(st.sampled_from(["replace", "replace", "scale", "drop", "add", "grow"]))
        value = parent[key]
        if action == "scale" and isinstance(value, int | float) and not isinstance(value, bool):
            parent[key] = value * draw(st.sampled_from([1e300, 1e150, 1e-300, -1.0, 0.0, 1e6]))
        elif action == "drop" and isinstance(parent, dict):
            del parent[key]
        elif action == "drop" and isinstance(parent, list):
            parent.pop(key)
        elif action == "add" and isinstance(value, dict):
            value[draw(st.text(max_size=6))] = draw(odd_values)
        elif action == "grow" and isinstance(value, list):
            value.append(copy.deepcopy(value[-1]) if value and draw(st.booleans()) else draw(odd_values))
        else:
            parent[key] = draw(odd_values)
    # No canonical bytes (NaN, a non-string key): the loader must refuse it all the same.
    with contextlib.suppress(TypeError, ValueError):
        content["crc32"] = f"0x{content_crc(content):08x}"
    return content


def _rows(cset: CoefficientSet) -> np.ndarray:
    lo, hi = cset.span_raw
    w = hi - lo
    return np.array([lo, hi, 0.5 * (lo + hi), lo - 1.0, hi + 1.0, lo - w, hi + w, lo - 2.0**32, hi + 2.0**32,
                     cset.v0, hi + 0.37 * w, lo - 0.73 * w])


def _check_finite(cset: CoefficientSet) -> None:
    corrector = Corrector(cset)
    raw = _rows(cset)
    n = raw.size
    levels = np.array([25.0, -1e6, 1e6, 0.0, 3.0, -40.0, 1e3, 25.5, 26.0, 24.0, -1e3, 1e6])[:n]
    inputs = {name: levels.copy() for name in corrector.required_inputs}
    if "time_s" in inputs:
        inputs["time_s"] = np.linspace(0.0, 1e6, n)
    rate, _ = corrector.correct(raw, inputs)
    assert np.isfinite(rate).all(), (rate, cset)
    one = Corrector(cset)
    fast = compile_corrector(Corrector(cset))
    for i in range(n):
        row = {k: float(v[i]) for k, v in inputs.items()}
        value, _ = one.correct_one(float(raw[i]), row)
        assert math.isfinite(value), (value, raw[i], cset)
        if fast is not None:
            assert math.isfinite(fast(float(raw[i]), row)[0])


def test_the_bases_load_and_are_finite() -> None:
    for content in BASES:
        _check_finite(loads(yaml.safe_dump(content)))


#: Examples per run (more for a longer hunt: CANICAL_VALIDATION_EXAMPLES=5000).
EXAMPLES = int(os.environ.get("CANICAL_VALIDATION_EXAMPLES", "400"))


@settings(max_examples=EXAMPLES, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(mutated())
def test_any_mutation_loads_finite_or_is_refused_in_one_line(content: dict[str, Any]) -> None:
    text = yaml.safe_dump(content)
    try:
        cset = loads(text, "mutated.yaml")
    except CanicalError as exc:
        message = str(exc)
        assert message.startswith("mutated.yaml: ") and "\n" not in message
        return
    _check_finite(cset)


@pytest.mark.parametrize(("path", "value", "field"), [
    (("model", "segment_points_dps"), [[1.0, 2.0], [3.0]], "model.segment_points_dps"),
    (("model", "coefficients", 0, 0), 1e308, "model.coefficients"),
    (("model", "coefficients", 2, 1), 1e300, "model.coefficients"),
    (("v0",), 1e308, "model"),
])
def test_the_known_holes_are_refused_in_one_line(path: tuple[Any, ...], value: Any, field: str) -> None:
    content = copy.deepcopy(BASES[0])
    _get(content, path[:-1])[path[-1]] = value
    content["crc32"] = f"0x{content_crc(content):08x}"
    with pytest.raises(CanicalError, match=field) as caught:
        loads(yaml.safe_dump(content), "holes.yaml")
    assert "\n" not in str(caught.value)


def test_a_term_coefficient_beyond_any_bound_is_refused() -> None:
    content = copy.deepcopy(BASES[1])
    content["terms"][0]["coefficient"] = 1e300
    content["crc32"] = f"0x{content_crc(content):08x}"
    with pytest.raises(CanicalError, match=r"terms\[0\]\.coefficient"):
        loads(yaml.safe_dump(content))


def test_a_forward_polynomial_flat_between_grid_points_is_refused() -> None:
    """Hypothesis's finding: ΔV(u) = 3 + 5e-324·u + 1.5e-299·u² + 120·u³ has a slope of 5e-324 at
    ω = 0, between the grid's points; it loaded, and Newton divided by zero per sample."""
    content = {"schema": 1, "sensor": {"id": "S1", "axis": "z"}, "units": {"raw": "counts", "rate": "deg/s"},
               "created": "2026", "v0": 12.0,
               "model": {"kind": "forward-poly", "coefficients": [3.0, 5e-324, 1.5e-299, 120.0],
                         "rate_scale": 60.0, "rate_span_dps": [-60.0, 60.0], "span_raw": [-24000.0, 24000.0],
                         "out_of_span": "linear-extrapolation"},
               "terms": [], "fit": {"rms_dps": 0.01}}
    content["crc32"] = f"0x{content_crc(content):08x}"
    with pytest.raises(CanicalError, match="forward polynomial without an inverse"):
        loads(yaml.safe_dump(content), "flat.yaml")
