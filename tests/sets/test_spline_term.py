"""The spline term (channel/spline): validated at load, evaluated identically by the block and
one-sample paths and the compiled corrector, bounded for the finite-output proof, and run by the
C evaluator (``canical push`` sends it)."""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
import pytest

from canical.commands.cli import main
from canical.errors import CanicalError
from canical.sets import coefficient_file
from canical.sets.coefficients import CoefficientSet
from canical.sets.corrector import Corrector
from canical.sets.fast_corrector import compile_corrector
from canical.sets.set_model import model_of
from canical.sets.term_kinds import CHANNEL_SPLINE, host_only, spline_one, spline_values
from canical.sets.terms import merge_splines, term_from_dict

MODEL = model_of({"kind": "segmented-inverse", "knots_raw": [-1000.0, 1000.0],
                  "segment_points_dps": [-10.0, 10.0], "scale": 1000.0,
                  "coefficients": [[0.1, 0.2, 0.003], [0.0, 0.25, 0.001], [0.2, 0.2, -0.002]],
                  "smoothness": 1, "span_raw": [-30000.0, 30000.0], "out_of_span": "linear-extrapolation"})


def spline_dict(rng: np.random.Generator, form: str, segments: int) -> dict[str, object]:
    knots = np.sort(rng.uniform(-5.0, 40.0, segments + 1))
    pieces = rng.normal(0.0, 1.0, (segments, 4)) * np.array([1.0, 0.3, 0.05, 0.01])
    return {"kind": "channel", "feature": "spline", "channel": "vib_g", "form": form,
            "coefficient": float(rng.normal(0.0, 20.0)), "reference": 0.0, "tau_s": None,
            "threshold_raw": None, "knots": knots.tolist(), "pieces": pieces.tolist()}


@pytest.mark.parametrize("seed", range(4))
def test_block_one_and_compiled_agree_bit_for_bit(seed: int) -> None:
    rng = np.random.default_rng(seed)
    terms = (spline_dict(rng, "bias", 1 + seed), spline_dict(rng, "scale", 5))
    cset = CoefficientSet("s", "z", 12.5, MODEL, tuple(term_from_dict(t) for t in terms))
    knots = terms[0]["knots"]
    n = 300
    v = np.concatenate([rng.uniform(-20.0, 60.0, n - 6), [knots[0], knots[-1], knots[1], -1e9, 1e9, 17]])  # type: ignore[index]
    raw = np.rint(rng.uniform(-20000.0, 20000.0, v.size))
    block, _ = Corrector(cset).correct(raw, {"vib_g": v})
    reference, fast_owner = Corrector(cset), Corrector(cset)
    compiled = compile_corrector(fast_owner)
    assert compiled is not None
    for i in range(v.size):
        row = {"vib_g": v[i].item() if i < v.size - 1 else 17}  # an int input too
        one, _ = reference.correct_one(raw[i], row)
        fast, _ = compiled(raw[i], row)
        assert struct.pack("<d", one) == struct.pack("<d", fast)
        assert struct.pack("<d", one) == struct.pack("<d", float(block[i]))


def test_spline_is_the_cubic_it_says_and_flat_beyond_its_knots() -> None:
    knots = (0.0, 1.0, 3.0)
    pieces = ((1.0, 2.0, 0.0, 0.0), (3.0, 0.5, -0.25, 0.125))
    v = np.array([-5.0, 0.0, 0.5, 1.0, 2.0, 3.0, 9.0])
    u2 = 1.0  # v = 2 lies 1 past the second knot
    expected = [1.0, 1.0, 2.0, 3.0, 3.0 + 0.5 * u2 - 0.25 * u2**2 + 0.125 * u2**3,
                3.0 + 0.5 * 2 - 0.25 * 4 + 0.125 * 8, 3.0 + 0.5 * 2 - 0.25 * 4 + 0.125 * 8]
    assert spline_values(knots, pieces, v) == pytest.approx(expected, abs=1e-15)
    assert [spline_one(knots, pieces, float(x)) for x in v] == pytest.approx(expected, abs=1e-15)
    assert np.isnan(spline_values(knots, pieces, np.array([np.nan])))[0]
    assert np.isnan(spline_one(knots, pieces, float("nan")))


@pytest.mark.parametrize("seed", range(3))
def test_reach_bounds_every_value(seed: int) -> None:
    rng = np.random.default_rng(seed)
    term = term_from_dict(spline_dict(rng, "bias", 4))
    v = np.concatenate([rng.uniform(-100.0, 100.0, 5000), np.asarray(term.params.knots)])
    x = CHANNEL_SPLINE.values(term, {"vib_g": v}, v, None)
    assert np.max(np.abs(x)) <= CHANNEL_SPLINE.reach(term, 1e9)


@pytest.mark.parametrize(("change", "message"), [
    ({"knots": [1.0]}, "knots must be a list of 2"),
    ({"knots": [0.0, 2.0, 1.0]}, "strictly increasing"),
    ({"knots": [0.0, 1.0, 1.0]}, "strictly increasing"),
    ({"knots": [0.0, float("inf"), 3.0]}, "knots must be a list"),
    ({"knots": None}, "knots must be a list"),
    ({"pieces": [[0.0, 0.0, 0.0, 0.0]]}, "pieces must be a list of 2 rows"),
    ({"pieces": [[0.0, 0.0, 0.0], [0.0, 0.0, 0.0, 0.0]]}, r"pieces\[0\] must be 4 finite"),
    ({"pieces": [[0.0, 0.0, 0.0, 0.0], [0.0, float("nan"), 0.0, 0.0]]}, r"pieces\[1\] must be 4 finite"),
    ({"channel": None}, "channel must name"),
])
def test_bad_spline_fields_are_refused_at_load(change: dict[str, object], message: str) -> None:
    good = {"kind": "channel", "feature": "spline", "channel": "vib_g", "form": "bias", "coefficient": 1.0,
            "knots": [0.0, 1.0, 3.0], "pieces": [[0.0, 1.0, 0.0, 0.0], [1.0, 1.0, 0.0, 0.0]]}
    assert term_from_dict(good).params.knots == (0.0, 1.0, 3.0)
    with pytest.raises(ValueError, match=message):
        term_from_dict({**good, **change})


def test_set_file_round_trip_and_other_terms_unchanged(tmp_path: Path) -> None:
    rng = np.random.default_rng(7)
    spline = term_from_dict(spline_dict(rng, "scale", 3))
    plain = term_from_dict({"kind": "channel", "feature": "offset", "channel": "t", "form": "bias",
                            "coefficient": 1.0})
    assert "knots" not in plain.to_dict() and "pieces" not in plain.to_dict()  # other sets keep their CRCs
    cset = CoefficientSet("123", "z", 12.5, MODEL, (spline, plain))
    path = tmp_path / "set.yaml"
    coefficient_file.save(path, cset)
    back = coefficient_file.load(path)
    assert back.terms[0] == spline
    assert coefficient_file.set_crc(back) == coefficient_file.set_crc(cset)


def test_the_c_evaluator_runs_a_set_with_a_spline() -> None:
    """The device's evaluator takes a spline set (its float32 agreement with apply, to a derived
    bound, is tests/device/firmware/test_firmware_spline.py); push has nothing to refuse."""
    rng = np.random.default_rng(3)
    terms = (spline_dict(rng, "bias", 3), spline_dict(rng, "scale", 5))
    cset = CoefficientSet("123", "z", 12.5, MODEL, tuple(term_from_dict(t) for t in terms))
    assert host_only(cset.terms) is None and host_only(()) is None
    from canical.device.firmware_eval import FirmwareCorrector, library

    try:
        library()
    except CanicalError as exc:  # no C compiler here
        pytest.skip(f"C evaluator not built: {exc}")
    v = np.float32(rng.uniform(-20.0, 60.0, 500)).astype(float)
    raw = np.rint(rng.uniform(-20000.0, 20000.0, v.size))
    rate, oos = FirmwareCorrector(cset, serial=123, axis="z").correct(raw, {"vib_g": v})
    expected, expected_oos = Corrector(cset).correct(raw, {"vib_g": v})
    np.testing.assert_array_equal(oos, expected_oos)
    assert np.max(np.abs(rate - expected)) < 1e-3 * np.max(np.abs(expected))


def test_push_refuses_a_kind_the_c_evaluator_lacks(tmp_path: Path, capsys, monkeypatch) -> None:
    """A kind without its C form yet (``c_name`` None, as a new kind lands first in Python) is
    refused by ``canical push`` in one line before any bus is opened."""
    rng = np.random.default_rng(3)
    cset = CoefficientSet("123", "z", 12.5, MODEL, (term_from_dict(spline_dict(rng, "bias", 3)),))
    path = tmp_path / "z.yaml"
    coefficient_file.save(path, cset)
    monkeypatch.setattr(type(CHANNEL_SPLINE), "c_name", None)
    assert host_only(cset.terms) == "terms[0] (channel/spline)"
    assert main(["push", str(path), "--node", "5", "--channel", "vcan-none", "--dry-run"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "terms[0] (channel/spline) is evaluated on the host only" in err[0]
    assert "not pushed" in err[0]


@pytest.mark.parametrize("form", ["bias", "scale"])
def test_merged_splines_correct_as_the_separate_terms(form: str) -> None:
    rng = np.random.default_rng(11)
    base = spline_dict(rng, form, 4)
    basis = [term_from_dict({**base, "coefficient": float(rng.normal(0.0, 30.0)),
                             "pieces": (rng.normal(0.0, 1.0, (4, 4)) * 0.1).tolist()}) for _ in range(3)]
    other = term_from_dict({"kind": "channel", "feature": "offset", "channel": "vib_g", "form": "bias",
                            "coefficient": 2.0, "reference": 1.0})
    terms = (basis[0], other, basis[1], basis[2])
    merged = merge_splines(terms)
    assert [t.feature for t in merged] == ["spline", "offset"] and merged[0].coefficient == 1.0
    assert merge_splines((other,)) == (other,)
    v = rng.uniform(-20.0, 60.0, 2000)
    raw = np.rint(rng.uniform(-20000.0, 20000.0, v.size))
    separate, _ = Corrector(CoefficientSet("s", "z", 12.5, MODEL, terms)).correct(
        raw, {"vib_g": v})
    one, _ = Corrector(CoefficientSet("s", "z", 12.5, MODEL, merged)).correct(
        raw, {"vib_g": v})
    assert one == pytest.approx(separate, rel=1e-12, abs=1e-12)
