"""Coefficient files: exact round trip, CRC, and one-line refusal of broken files."""

import numpy as np
import pytest
import yaml
from hypothesis import given, settings
from hypothesis import strategies as st

from canical.errors import CanicalError
from canical.models.kinds import SEGMENTED_INVERSE
from canical.models.piecewise import PiecewisePoly
from canical.sets import coefficient_file
from canical.sets.coefficients import CoefficientSet, piecewise_model
from canical.sets.corrector import Corrector

finite = st.floats(min_value=-1e6, max_value=1e6, allow_nan=False, allow_infinity=False)


@st.composite
def coefficient_sets(draw):
    n_seg = draw(st.integers(1, 6))
    order = draw(st.integers(1, 4))
    edges = sorted(draw(st.lists(finite, min_size=n_seg + 1, max_size=n_seg + 1, unique=True)))
    coeffs = np.array(draw(st.lists(st.lists(finite, min_size=order + 1, max_size=order + 1),
                                    min_size=n_seg, max_size=n_seg)))
    scale = draw(st.floats(min_value=1e-3, max_value=1e6))
    poly = PiecewisePoly(np.array(edges[1:-1]), coeffs, scale, (edges[0], edges[-1]))
    v0 = draw(finite)
    smoothness = draw(st.sampled_from([None, 0, 1]))
    model = piecewise_model(SEGMENTED_INVERSE, poly, 0.0, smoothness=smoothness,
                                 segment_points_dps=[0.0] * (n_seg - 1))
    sensor = draw(st.text(st.characters(codec="utf-8", exclude_categories=["Cs", "Cc"]), min_size=1,
                          max_size=20))
    return CoefficientSet(sensor, draw(st.sampled_from(["x", "y", "z"])), v0, model,
                          fit={"held_out_rms_dps": draw(finite)}, created="2026-01-01T00:00:00Z")


@settings(max_examples=60, deadline=None)
@given(coefficient_sets())
def test_round_trip_is_exact(cset):
    text = coefficient_file.dumps(cset)
    back = coefficient_file.loads(text)
    assert back == cset
    assert coefficient_file.dumps(back) == text


def make_set() -> CoefficientSet:
    poly = PiecewisePoly(np.array([-1000.0, 2000.0]), np.array([[0, 60, 1], [0, 60, 0], [0, 61, -1.0]]),
                         20000.0, (-20000.0, 20000.0))
    model = piecewise_model(SEGMENTED_INVERSE, poly, 10.0, smoothness=0, segment_points_dps=[-15, 30])
    return CoefficientSet("IMU-7", "z", 10.0, model, created="2026-01-01T00:00:00Z")


def test_save_writes_atomically_and_loads(tmp_path):
    path = tmp_path / "c.yaml"
    coefficient_file.save(path, make_set())
    assert coefficient_file.load(path) == make_set()
    assert [p.name for p in tmp_path.iterdir()] == ["c.yaml"]


def edited(mutate, fix_crc=True) -> str:
    content = yaml.safe_load(coefficient_file.dumps(make_set()))
    mutate(content)
    if fix_crc:
        content["crc32"] = f"0x{coefficient_file.content_crc(content):08x}"
    return yaml.safe_dump(content, sort_keys=False)


@pytest.mark.parametrize(
    ("mutate", "fix_crc", "message"),
    [
        (lambda c: c["model"]["coefficients"][0].__setitem__(1, 61.0), False, "CRC mismatch"),
        (lambda c: c.pop("crc32"), False, "crc32 missing"),
        (lambda c: c.__setitem__("schema", 99), True, "schema 99 not supported"),
        (lambda c: c["model"].__setitem__("kind", "magic"), True, "model.kind 'magic' unknown"),
        (lambda c: c["model"]["knots_raw"].reverse(), True, "strictly ascending"),
        (lambda c: c["model"]["coefficients"].pop(), True, "one row per segment"),
        (lambda c: c["model"]["span_raw"].reverse(), True, "span_raw must be ascending"),
        (lambda c: c["model"].__setitem__("scale", -1.0), True, "scale must be a positive"),
        (lambda c: c.__setitem__("v0", "high"), True, "v0 must be a finite number"),
        (lambda c: c["sensor"].__setitem__("id", ""), True, "sensor.id"),
        (lambda c: c.__setitem__("terms", [{"kind": "gravity"}]), True, "terms[0]: kind 'gravity'"),
        (lambda c: c["model"]["knots_raw"].__setitem__(0, -1e9), True, "inside model.span_raw"),
    ],
)
def test_broken_files_are_refused_with_one_line(mutate, fix_crc, message):
    with pytest.raises(CanicalError) as info:
        coefficient_file.loads(edited(mutate, fix_crc), "c.yaml")
    text = str(info.value)
    assert message in text and text.startswith("c.yaml: ") and "\n" not in text


def test_not_yaml_and_not_mapping():
    with pytest.raises(CanicalError, match="not valid YAML"):
        coefficient_file.loads("a: [1,", "c.yaml")
    with pytest.raises(CanicalError, match="expected a mapping"):
        coefficient_file.loads("- 1\n- 2\n", "c.yaml")


def test_file_without_optional_keys_still_loads():
    """Older files written before 'terms' and 'fit' existed keep loading."""
    def drop(c):
        c.pop("terms")
        c.pop("fit")
    back = coefficient_file.loads(edited(drop))
    assert back.terms == () and back.fit == {}


def test_set_id_is_the_crc_and_identifies_content():
    a = Corrector(make_set())
    assert f"0x{a.set_id:08x}" == yaml.safe_load(coefficient_file.dumps(make_set()))["crc32"]
