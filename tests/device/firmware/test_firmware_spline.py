"""Spline terms in the firmware's C evaluator: any valid spline corrects as `canical apply` does, to
a float32 error bound derived from the pieces and the knot spacing; bad splines are refused as
canical refuses them; the device's spline limits are canical's."""

from __future__ import annotations

import json
import re
import zlib
from dataclasses import replace

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from support.firmware_build import (
    CODES,
    EPS32,
    FIRMWARE,
    TOLERANCE_DPS,
    load_code,
    python_verdict,
    steepest_slope,
)
from support.firmware_cases import ALL_TERMS, hermite_pieces, model_set, stream

from canical.device.bank_payload import encode_set
from canical.device.firmware_eval import FirmwareCorrector
from canical.sets import coefficient_file
from canical.sets.admission import MAX_SPLINE_TERMS, MAX_TERMS
from canical.sets.coefficients import CoefficientSet
from canical.sets.corrector import Corrector
from canical.sets.term_kinds import MAX_SPLINE_KNOTS, spline_values
from canical.sets.terms import term_from_dict

# ----------------------------------------------------------------------------------------------
# The float32 error of a spline term, derived
# ----------------------------------------------------------------------------------------------
#
# M = max over segments i of Σ_j |a_ij|·h_i^j (h_i the segment's width; what
# ChannelSpline.reach gives): |S| ≤ M, and every partial sum of Horner's scheme is within M.
# With ε = 2^-24, the C evaluator's S differs from canical's double one by at most
#   ε·M    the pieces rounded to float32 (|δa_j| ≤ ε|a_j|, times |u|^j ≤ h^j),
#   6ε·M   u = (w − b_hi) − b_lo: two roundings, |δu| ≤ 2ε|u|, and |u·S'(u)| ≤ Σ j|a_j||u|^j ≤ 3M,
#   6ε·M   Horner: three multiply-adds, six roundings, each within ε of a partial sum (≤ M),
# so |ΔS| ≤ 13ε·M (to first order; the segment is the same: the knots are float pairs and the
# variable is a float32 number, the channel's value or the raw output). A rate spline's knots
# are held in raw counts (b + V0, rounded in double: within 2^-50·|b + V0|), which moves u by
# that much more: M₁·2^-50·max|b + V0|, M₁ = max Σ j|a_j|·h^(j-1) the steepest S can get.
# x = S (spline): the share c·S adds the coefficient's rounding and the product's, 2ε·|c|·M, so
# the bias form's shift is within 15ε·|c|·M; the scale form c·(S·ΔV) adds ΔV = (raw − V0_hi) −
# V0_lo (2ε|ΔV|) and one more product: 18ε·|c|·M·max|ΔV|.
# x = (v − ref)·R (rate spline), A = max|v − ref|: ref rounded (ε|ref|) and the subtraction
# (ε·A), the product (ε·A·M), on top of A·|ΔR|: ε·M·(15A + |ref|); the share adds 2ε·|c|·A·M
# (bias) or, with ΔV, 4ε·|c|·A·M·|ΔV| (scale).
# The rate moves with the shift at most by the model's steepest slope G (deg/s per count;
# beyond the span the model extrapolates with its edge slope, within G), on top of the model's
# own float32 error (TOLERANCE_DPS, as for every set without terms).

#: The spline kinds (their x; the variable of S: the channel, or the output's ΔV).
SPLINE_FEATURES = ("spline", "rate_spline")


def shift_bound(term: dict, dv_max: float, v: np.ndarray, v0: float) -> float:
    """The largest float32 error of the term's share of ΔV (counts), as derived above."""
    knots = np.asarray(term["knots"])
    pieces = np.abs(np.asarray(term["pieces"]))
    h = np.diff(knots)[:, None]
    m = float(np.max(np.sum(pieces * h ** np.arange(4), axis=1)))
    c = abs(term["coefficient"])
    dv = dv_max if term["form"] == "scale" else 1.0
    if term["feature"] == "spline":
        return (15 if term["form"] == "bias" else 18) * EPS32 * c * m * dv
    m1 = float(np.max(np.sum(pieces[:, 1:] * np.arange(1, 4) * h ** np.arange(3), axis=1)))
    a = float(np.max(np.abs(v - term["reference"])))
    ds = 13 * EPS32 * m + m1 * 2.0**-50 * float(np.max(np.abs(knots + v0)))
    dx = a * ds + EPS32 * m * (2 * a + abs(term["reference"]))
    return c * dv * (dx + (2 if term["form"] == "bias" else 4) * EPS32 * a * m)


def with_term(term: dict) -> CoefficientSet:
    """The calibrated segmented set with ``term``, through the file format."""
    cset = replace(model_set("segmented-inverse"), terms=(term_from_dict(term),))
    return coefficient_file.loads(coefficient_file.dumps(cset))


def term_x(term: dict, v: np.ndarray, dv: np.ndarray) -> np.ndarray:
    """canical's x of a spline kind (to tell where a span edge lies within the bound)."""
    knots, pieces = tuple(term["knots"]), tuple(map(tuple, term["pieces"]))
    if term["feature"] == "spline":
        return spline_values(knots, pieces, v)
    return (v - term["reference"]) * spline_values(knots, pieces, dv)


@st.composite
def spline_terms(draw) -> dict:
    """A valid spline term: 2 to 64 knots, some of them exactly where samples land (float32
    channel values; for a rate spline, ΔV of whole raw counts), pieces of any sign whose each
    power moves S by up to `size` over a segment (discontinuous at the knots: a wrong segment
    would show), either form."""
    feature = draw(st.sampled_from(SPLINE_FEATURES))
    n = draw(st.integers(2, MAX_SPLINE_KNOTS))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    on = rng.random(n) < 0.5
    if feature == "spline":
        knots = rng.uniform(0.0, 50.0, n)
        knots[on] = knots[on].astype(np.float32)
    else:  # ΔV in raw counts, across the span and beyond it
        v0 = model_set("segmented-inverse").v0
        knots = rng.uniform(-35000.0, 35000.0, n)
        knots[on] = np.rint(knots[on] + v0) - v0
    knots = np.unique(knots)
    if knots.size < 2:
        knots = np.array([10.0, 30.0])
    widths = np.diff(knots)
    size = draw(st.floats(0.01, 10.0))
    pieces = rng.normal(0.0, size, (widths.size, 4)) / widths[:, None] ** np.arange(4)
    form = draw(st.sampled_from(("bias", "scale")))
    largest = {("spline", "bias"): 50.0, ("spline", "scale"): 2e-3,
               ("rate_spline", "bias"): 5.0, ("rate_spline", "scale"): 1e-4}[feature, form]
    return {"kind": "channel", "feature": feature, "channel": "temp_c", "form": form,
            "coefficient": draw(st.floats(-largest, largest)), "reference": draw(st.floats(0.0, 40.0)),
            "knots": knots.tolist(), "pieces": pieces.tolist()}


def channel_values(term: dict, n: int, rng: np.random.Generator) -> np.ndarray:
    """float32 numbers (what the device gets): a spline's across its knots, on them and beyond
    both ends; a rate spline's within 20 of its reference."""
    if term["feature"] != "spline":
        v = rng.uniform(term["reference"] - 20.0, term["reference"] + 20.0, n)
        return v.astype(np.float32).astype(float)
    knots = np.asarray(term["knots"])
    lo, hi = knots[0], knots[-1]
    v = rng.uniform(lo - 5.0, hi + 5.0, n)
    on_knot = rng.random(n) < 0.1
    v[on_knot] = rng.choice(knots, int(on_knot.sum()))
    return v.astype(np.float32).astype(float)


def assert_like_canical(cset, raw: np.ndarray, shift: np.ndarray, bound: float,
                        got: tuple[np.ndarray, np.ndarray], expected: tuple[np.ndarray, np.ndarray]) -> None:
    """The C evaluator's rates within the derived float32 ``bound`` of canical's (through the set's
    steepest slope), the same out-of-span flags except where ``shift ± bound`` straddles a span edge."""
    (rate, oos), (want, want_oos) = got, expected
    lo, hi = cset.span_raw
    edge = np.minimum(np.abs(raw - shift - lo), np.abs(raw - shift - hi)) <= bound
    np.testing.assert_array_equal(oos[~edge], want_oos[~edge])
    worst = float(np.max(np.abs(rate - want)))
    allowed = TOLERANCE_DPS + steepest_slope(cset) * bound
    assert worst <= allowed, f"largest difference {worst:.3e} deg/s, bound {allowed:.3e}"


@settings(max_examples=80, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(term=spline_terms(), seed=st.integers(0, 1000))
def test_property_any_spline_evaluates_like_canical(lib_for_hypothesis, term, seed):
    """Any valid spline term: the C evaluator's rates within the derived float32 bound of
    canical's, and the same out-of-span flags (except where the shift's own bound straddles a
    span edge)."""
    cset = with_term(term)
    raw, inputs = stream(cset, 3000, seed=seed)
    rng = np.random.default_rng(seed)
    dv = raw - cset.v0
    if term["feature"] != "spline":  # ΔV on the knots that lie on whole counts too
        on = np.rint(np.asarray(term["knots"]) + cset.v0)
        hit = rng.random(raw.size) < 0.1
        raw = np.where(hit, rng.choice(on, raw.size), raw)
        dv = raw - cset.v0
    inputs = {**inputs, "temp_c": channel_values(term, raw.size, rng)}
    expected, expected_oos = Corrector(cset).correct(raw, inputs)
    rate, oos = FirmwareCorrector(cset, lib=lib_for_hypothesis).correct(raw, inputs)
    bound = shift_bound(term, float(np.max(np.abs(dv))), inputs["temp_c"], cset.v0)
    x = term_x(term, inputs["temp_c"], dv)
    shift = term["coefficient"] * (x * dv if term["form"] == "scale" else x)
    assert_like_canical(cset, raw, shift, bound, (rate, oos), (expected, expected_oos))


def test_the_bound_is_not_vacuous_a_wrong_segment_breaks_it(lib):
    """The derived bound is tight enough to see a segment chosen one knot off: the same set with
    each piece moved to the next segment gives rates far beyond it."""
    term = dict(ALL_TERMS["channel-spline"], coefficient=5.0)
    shifted = dict(term, pieces=[*term["pieces"][1:], term["pieces"][-1]])
    right, wrong = with_term(term), with_term(shifted)
    raw, inputs = stream(right, 3000, seed=1)
    expected, _ = Corrector(right).correct(raw, inputs)
    rate, _ = FirmwareCorrector(wrong, lib=lib).correct(raw, inputs)
    bound = shift_bound(term, float(np.max(np.abs(raw - right.v0))), inputs["temp_c"], right.v0)
    allowed = TOLERANCE_DPS + steepest_slope(right) * bound
    assert float(np.max(np.abs(rate - expected))) > 100 * allowed


# ----------------------------------------------------------------------------------------------
# Validation: what canical refuses the device refuses
# ----------------------------------------------------------------------------------------------


def spline_bank(*terms: dict) -> dict:
    base = model_set("segmented-inverse")
    cset = replace(base, terms=tuple(term_from_dict(t) for t in terms))
    return json.loads(encode_set(cset)[0])


def edited(change) -> tuple[bytes, int]:
    d = spline_bank(ALL_TERMS["channel-spline"])
    change(d["terms"][0])
    content = json.dumps(d, sort_keys=True, separators=(",", ":")).encode()
    return content, zlib.crc32(content)


def _set(**fields):
    return lambda t: t.update(fields)


def _drop(name):
    return lambda t: t.pop(name)


KNOTS = ALL_TERMS["channel-spline"]["knots"]
PIECES = ALL_TERMS["channel-spline"]["pieces"]
REFUSALS = {
    "one knot": (_set(knots=[1.0], pieces=[]), "CE_ERR_FIELD"),
    "knots not increasing": (_set(knots=[KNOTS[1], KNOTS[0], *KNOTS[2:]]), "CE_ERR_FIELD"),
    "a repeated knot": (_set(knots=[KNOTS[0], KNOTS[0], *KNOTS[2:]]), "CE_ERR_FIELD"),
    "knots not numbers": (_set(knots="0 1 2"), "CE_ERR_FIELD"),
    "a knot not a number": (_set(knots=[*KNOTS[:-1], "46"]), "CE_ERR_FIELD"),
    "no knots": (_drop("knots"), "CE_ERR_FIELD"),
    "no pieces": (_drop("pieces"), "CE_ERR_FIELD"),
    "a row too few": (_set(pieces=PIECES[:-1]), "CE_ERR_FIELD"),
    "a row too many": (_set(pieces=[*PIECES, PIECES[0]]), "CE_ERR_FIELD"),
    "a row of 3": (_set(pieces=[PIECES[0][:3], *PIECES[1:]]), "CE_ERR_FIELD"),
    "a row of 5": (_set(pieces=[[*PIECES[0], 0.0], *PIECES[1:]]), "CE_ERR_FIELD"),
    "a row not a list": (_set(pieces=[1.0, *PIECES[1:]]), "CE_ERR_FIELD"),
    "no channel": (_drop("channel"), "CE_ERR_FIELD"),
    "more knots than 64": (_set(knots=list(np.linspace(0.0, 50.0, MAX_SPLINE_KNOTS + 1)),
                                pieces=[[0.0, 0.0, 0.0, 0.0]] * MAX_SPLINE_KNOTS), "CE_ERR_LIMIT"),
}


@pytest.mark.parametrize("case", list(REFUSALS))
def test_bad_splines_are_refused_by_the_device_and_by_canical(lib, case):
    change, code = REFUSALS[case]
    content, crc = edited(change)
    assert load_code(lib, content, crc) == CODES[code]
    assert python_verdict(content, crc) is not None


def test_what_only_the_device_refuses_canical_push_refuses_before_writing(lib):
    """More spline terms than CE_MAX_SPLINES, or a piece beyond float32: the device's own limits;
    canical's admission (which push and export run before writing) names the same."""
    too_many = spline_bank(*(dict(ALL_TERMS["channel-spline"], coefficient=0.5 * (i + 1))
                             for i in range(MAX_SPLINE_TERMS + 1)))
    huge = spline_bank(dict(ALL_TERMS["channel-spline"], pieces=[[1e39, 0.0, 0.0, 0.0], *PIECES[1:]]))
    far = spline_bank(dict(ALL_TERMS["channel-spline"], knots=[*KNOTS[:-1], 1e39]))
    wide = spline_bank(dict(ALL_TERMS["channel-spline"], knots=[-2e38, 2e38], pieces=PIECES[:1]))
    for d, words in ((too_many, "spline terms"), (huge, "float32"), (far, "float32"), (wide, "spacing")):
        content = json.dumps(d, sort_keys=True, separators=(",", ":")).encode()
        assert load_code(lib, content, zlib.crc32(content)) == CODES["CE_ERR_LIMIT"]
        assert words in (python_verdict(content, zlib.crc32(content)) or "")
    most = spline_bank(*(dict(ALL_TERMS["channel-spline"], coefficient=0.5 * (i + 1))
                         for i in range(MAX_SPLINE_TERMS)))
    content = json.dumps(most, sort_keys=True, separators=(",", ":")).encode()
    assert load_code(lib, content, zlib.crc32(content)) == 0
    assert python_verdict(content, zlib.crc32(content)) is None


def test_knots_on_another_kind_are_ignored_as_canical_ignores_them(lib):
    d = spline_bank(ALL_TERMS["channel-offset"])
    d["terms"][0].update(knots=[0.0, 1.0], pieces="anything")
    content = json.dumps(d, sort_keys=True, separators=(",", ":")).encode()
    assert load_code(lib, content, zlib.crc32(content)) == 0
    assert python_verdict(content, zlib.crc32(content)) is None


def test_the_device_limits_are_canicals():
    header = (FIRMWARE / "canical_eval.h").read_text()

    def limit(name: str) -> int:
        found = re.search(rf"#define {name} (\d+)", header)
        assert found, name
        return int(found.group(1))

    assert limit("CE_MAX_SPLINE_KNOTS") == MAX_SPLINE_KNOTS
    assert limit("CE_MAX_SPLINES") == MAX_SPLINE_TERMS
    assert limit("CE_MAX_TERMS") == MAX_TERMS


@pytest.mark.parametrize("effect", ["smooth(load)", "smooth(temp_c × rate)"])
def test_a_learned_smooth_effect_runs_on_the_device_as_apply(lib, effect):
    """What the closed loop writes for a smooth effect (a channel's spline; a coefficient that
    changes with rate), corrected by the C evaluator on the session's own samples (channels as
    float32, as a device has them): within the derived bounds of apply, flags alike."""
    from canical.calibration.pipeline import CalibrateOptions, calibrate
    from canical.sim.scenarios import SMOOTH_SCENARIOS

    scenario = next(s for s in SMOOTH_SCENARIOS if effect in s.expect)
    for seed in range(5):  # the first seed whose set holds the spline (a nested form may win a draw)
        session = scenario.session(seed=seed, dwell_s=8.0)
        cset = calibrate(session, CalibrateOptions(), sensor_id="4711", axis="z").coefficients
        splines = [t.to_dict() for t in cset.terms if t.feature in ("spline", "rate_spline")]
        if splines:
            break
    assert splines, [t.feature for t in cset.terms]
    inputs = {k: np.asarray(v, dtype=np.float32).astype(float) for k, v in session.aux.items()}
    inputs["time_s"] = session.time_s
    raw = session.raw
    expected, expected_oos = Corrector(cset).correct(raw, inputs)
    rate, oos = FirmwareCorrector(cset, lib=lib).correct(raw, inputs)
    np.testing.assert_array_equal(oos, expected_oos)
    dv_max = float(np.max(np.abs(raw - cset.v0)))
    bound = sum(shift_bound(t, dv_max, inputs[t["channel"]], cset.v0) for t in splines)
    worst = float(np.max(np.abs(rate - expected)))
    assert worst <= TOLERANCE_DPS + steepest_slope(cset) * bound, worst


# ----------------------------------------------------------------------------------------------
# The smooth form of a lag or of a rate of change: the lag's state, then spline_at
# ----------------------------------------------------------------------------------------------
#
# x = S(y) (lag_spline) or S((v − y)/τ) (derivative_spline). The device's variable differs from
# canical's by δ: for a lag, v reaches it as float32 (ε·max|v|), y is the lag of those (weights
# summing to 1: ε·max|v|), and the float pair y is rounded once into spline_at (ε·max|v|), a few
# ε·R more for the lag's steps (R the spread of v): δ ≤ ε·(3·max|v| + 6R); for a rate of change
# δ is the derivative's own (test_firmware_accuracy.derivative_shift_bound): ε·(2·max|v| + 8R)/τ
# plus 2ε·R/τ. S is continuous here (Hermite pieces), so a δ across a knot moves S by at most
# M₁·δ (M₁ = max Σ j|a_j|·h^(j−1)) whatever segment each side chose; the spline's own steps add
# 13ε·M as above and the share 2ε·|c|·M (bias) or 5ε·|c|·M·|ΔV| (scale).

TRANSFORM_SPLINES = ("lag_spline", "derivative_spline")


def transform_shift_bound(term: dict, values: np.ndarray, dv_max: float) -> float:
    """The largest float32 error of a lag or derivative spline's share of ΔV (counts), as derived above."""
    knots = np.asarray(term["knots"])
    pieces = np.abs(np.asarray(term["pieces"]))
    h = np.diff(knots)[:, None]
    m = float(np.max(np.sum(pieces * h ** np.arange(4), axis=1)))
    m1 = float(np.max(np.sum(pieces[:, 1:] * np.arange(1, 4) * h ** np.arange(3), axis=1)))
    v_max, spread = float(np.max(np.abs(values))), float(np.ptp(values))
    if term["feature"] == "lag_spline":
        delta = EPS32 * (3.0 * v_max + 6.0 * spread)
    else:
        delta = EPS32 * (2.0 * v_max + 10.0 * spread) / term["tau_s"]
    dx = m1 * delta + 13.0 * EPS32 * m
    c = abs(term["coefficient"])
    if term["form"] == "bias":
        return c * (dx + 2.0 * EPS32 * m)
    return c * dv_max * (dx + 5.0 * EPS32 * m)


@st.composite
def transform_spline_terms(draw) -> dict:
    """A lag or derivative spline: 2 to 64 knots over (or beyond) the variable's range, a
    continuous S through a random saturating curve (Hermite pieces), any τ, either form."""
    feature = draw(st.sampled_from(TRANSFORM_SPLINES))
    n = draw(st.integers(2, MAX_SPLINE_KNOTS))
    rng = np.random.default_rng(draw(st.integers(0, 2**32 - 1)))
    scale = 20.0 if feature == "lag_spline" else 0.05  # °C, or °C/s
    centre = 25.0 if feature == "lag_spline" else 0.0
    knots = np.unique(rng.uniform(centre - 1.5 * scale, centre + 1.5 * scale, n))
    if knots.size < 2:
        knots = np.array([centre - scale, centre + scale])
    amp, mid = rng.uniform(-60.0, 60.0), centre + rng.uniform(-0.5, 0.5) * scale
    width = scale * rng.uniform(0.1, 1.0)
    pieces = hermite_pieces(knots.tolist(), lambda x: amp * np.tanh((x - mid) / width),
                     lambda x: amp / width / np.cosh((x - mid) / width) ** 2)
    form = draw(st.sampled_from(("bias", "scale")))
    return {"kind": "channel", "feature": feature, "channel": "temp_c", "form": form,
            "coefficient": draw(st.floats(-1.0, 1.0)) * (1.0 if form == "bias" else 4e-5),
            "tau_s": draw(st.floats(0.5, 300.0)), "knots": knots.tolist(), "pieces": pieces}


@settings(max_examples=60, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(term=transform_spline_terms(), seed=st.integers(0, 1000))
def test_property_a_lag_or_derivative_spline_evaluates_like_canical(lib_for_hypothesis, term, seed):
    """Any smooth form of a channel's lag or rate of change: the C evaluator (the lag's state, then
    spline_at) within the derived float32 bound of canical's rates, the same out-of-span flags
    (except where the shift's own bound straddles a span edge)."""
    cset = with_term(term)
    raw, inputs = stream(cset, 4000, seed=seed)
    expected, expected_oos = Corrector(cset).correct(raw, inputs)
    rate, oos = FirmwareCorrector(cset, lib=lib_for_hypothesis).correct(raw, inputs)
    dv = raw - cset.v0
    bound = transform_shift_bound(term, inputs["temp_c"], float(np.max(np.abs(dv))))
    parsed = term_from_dict(term)
    x = parsed.spec.values(parsed, inputs, raw, dv)
    shift = term["coefficient"] * (x * dv if term["form"] == "scale" else x)
    assert_like_canical(cset, raw, shift, bound, (rate, oos), (expected, expected_oos))
