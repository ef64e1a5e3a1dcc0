"""Effect terms at run time: validation, trackers, and block and per-sample paths agreeing."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canical.models.kinds import SEGMENTED_INVERSE
from canical.models.piecewise import PiecewisePoly
from canical.sets.coefficients import CoefficientSet, piecewise_model
from canical.sets.corrector import Corrector
from canical.sets.terms import (
    ChannelTracker,
    DirectionTracker,
    SlopeTracker,
    feature_values,
    lag_filter,
    term_from_dict,
)


def test_direction_tracker_has_hysteresis():
    t = DirectionTracker(10.0)
    seq = [0, 5, 11, 8, 15, 4, 3, 20, 9]
    states = [t.update(v) for v in seq]
    assert states == [0, 0, 1, 1, 1, -1, -1, 1, -1]


def test_slope_tracker_converges_to_the_ramp_slope():
    t = SlopeTracker(0.1)
    out = [t.update(3.0 * k * 0.01, k * 0.01) for k in range(500)]
    assert out[-1] == pytest.approx(3.0)


def test_channel_lag_and_derivative_follow_a_ramp():
    """After a ramp has run many τ, the lag trails it by slope·τ and the derivative is the slope."""
    lag = ChannelTracker(20.0, reference=1.0)
    der = ChannelTracker(20.0, derivative=True)
    times = np.arange(0, 400, 0.05)
    for t in times:
        x_lag, x_der = lag.update(0.5 * t, t), der.update(0.5 * t, t)
    # Exact discrete lag: it trails by slope·(τ − dt/2) to first order in dt/τ.
    assert x_der == pytest.approx(0.5 * (1 - 0.05 / 40.0), rel=1e-5)
    assert x_lag == pytest.approx(0.5 * times[-1] - 0.5 * (20.0 - 0.025) - 1.0, rel=1e-5)
    fresh = ChannelTracker(5.0, derivative=True)
    assert fresh.update(3.0, 0.0) == 0.0  # no change seen yet


@settings(max_examples=30, deadline=None)
@given(st.integers(0, 2**32 - 1), st.booleans(), st.floats(0.5, 500.0))
def test_vectorised_lag_equals_the_tracker(seed, even, tau):
    """The calibration's vectorised lag is the run-time tracker's, evenly spaced samples or not."""
    rng = np.random.default_rng(seed)
    n = 400
    t = np.arange(n) * 0.01 if even else np.cumsum(rng.uniform(0.001, 0.05, n))
    v = np.cumsum(rng.normal(0, 1, n))
    tracker = ChannelTracker(tau)
    one = [tracker.update(a, b) for a, b in zip(v.tolist(), t.tolist(), strict=True)]
    np.testing.assert_allclose(lag_filter(v, t, tau), one, rtol=1e-9, atol=1e-9)


@pytest.mark.parametrize(
    ("term", "message"),
    [
        ({"kind": "gravity", "feature": "x", "form": "bias", "coefficient": 1.0}, "kind 'gravity'"),
        ({"kind": "channel", "feature": "warmup", "form": "bias", "coefficient": 1.0, "channel": "t"},
         "feature 'warmup' not valid"),
        ({"kind": "channel", "feature": "offset", "form": "gain", "coefficient": 1.0, "channel": "t"},
         "form 'gain'"),
        ({"kind": "time", "feature": "warmup", "form": "bias", "coefficient": 1.0}, "tau_s"),
        ({"kind": "direction", "feature": "sign", "form": "bias", "coefficient": 1.0}, "threshold_raw"),
        ({"kind": "channel", "feature": "offset", "form": "bias", "coefficient": float("nan"),
          "channel": "t"}, "coefficient"),
        ({"kind": "channel", "feature": "lag", "form": "bias", "coefficient": 1.0, "channel": "t"}, "tau_s"),
        ({"kind": "channel", "feature": "derivative", "form": "scale", "coefficient": 1.0, "channel": "t",
          "tau_s": -2.0}, "tau_s must be positive"),
        ({"kind": "time", "feature": "warmup", "form": "scale", "coefficient": 1.0, "tau_s": 5e-324},
         r"tau_s 4.94e-324 s is outside 1e-06..1e\+09 s"),  # t/τ overflowed (the fuzzer's finding)
        ({"kind": "channel", "feature": "lag", "form": "bias", "coefficient": 1.0, "channel": "t",
          "tau_s": 1e300}, "tau_s 1e\\+300 s is outside"),
        ({"kind": "channel", "feature": "direction", "form": "bias", "coefficient": 1.0, "channel": "t"},
         "threshold_raw"),
        ({"kind": "channel", "feature": "gated", "form": "scale", "coefficient": 1.0, "channel": "t"},
         "threshold_raw"),
        ({"kind": "channel", "feature": "gated", "form": "scale", "coefficient": 1.0, "channel": "t",
          "threshold_raw": 0.0}, "threshold_raw must be positive"),
    ],
)
def test_bad_terms_are_refused(term, message):
    with pytest.raises(ValueError, match=message):
        term_from_dict(term)


ALL_TERMS = (
    {"kind": "channel", "channel": "temp_c", "feature": "offset", "form": "bias", "coefficient": -0.01,
     "reference": 25.0},
    {"kind": "channel", "channel": "temp_c", "feature": "square", "form": "bias", "coefficient": 1e-4,
     "reference": 25.0},
    {"kind": "channel", "channel": "supply_v", "feature": "offset", "form": "scale", "coefficient": 0.3,
     "reference": 5.0},
    {"kind": "time", "feature": "warmup", "form": "bias", "coefficient": 0.2, "tau_s": 120.0},
    {"kind": "time", "feature": "linear", "form": "scale", "coefficient": 1e-5},
    {"kind": "direction", "feature": "sign", "form": "bias", "coefficient": 0.05, "threshold_raw": 400.0},
    {"kind": "direction", "feature": "slope", "form": "bias", "coefficient": 1e-5, "tau_s": 0.5},
    {"kind": "channel", "channel": "temp_c", "feature": "gated", "form": "scale", "coefficient": 3e-4,
     "reference": 25.0, "threshold_raw": 2000.0},
    {"kind": "channel", "channel": "supply_v", "feature": "gated", "form": "bias", "coefficient": -40.0,
     "reference": 5.0, "threshold_raw": 900.0},
    {"kind": "channel", "channel": "temp_c", "feature": "lag", "form": "bias", "coefficient": 0.02,
     "reference": 25.0, "tau_s": 140.0},
    {"kind": "channel", "channel": "temp_c", "feature": "derivative", "form": "scale", "coefficient": 3e-3,
     "tau_s": 2.0},
    {"kind": "channel", "channel": "temp_c", "feature": "derivative", "form": "bias", "coefficient": 4.0,
     "tau_s": 0.3},
    {"kind": "channel", "channel": "supply_v", "feature": "direction", "form": "bias", "coefficient": 0.7,
     "threshold_raw": 0.2},
)


def extended_set() -> CoefficientSet:
    poly = PiecewisePoly(np.array([-3000.0, 5000.0]),
                         np.array([[0.1, 60.0, 1.0], [0.0, 60.5, 0.0], [0.2, 59.0, -1.0]]), 24000.0,
                         (-24000.0, 24000.0))
    model = piecewise_model(SEGMENTED_INVERSE, poly, 30.0, smoothness=None, segment_points_dps=[-7.0, 12.0])
    return CoefficientSet("S", "z", 30.0, model, terms=tuple(term_from_dict(t) for t in ALL_TERMS))


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1))
def test_block_and_per_sample_corrections_agree(seed):
    rng = np.random.default_rng(seed)
    n = 600
    raw = np.cumsum(rng.normal(0, 300, n)) + rng.normal(0, 30, n)
    inputs = {"temp_c": rng.uniform(-20, 60, n), "supply_v": rng.uniform(4.5, 5.5, n),
              "time_s": np.cumsum(rng.uniform(0.001, 0.05, n))}
    block, flags = Corrector(extended_set()).correct(raw, inputs)
    one = Corrector(extended_set())
    for i in range(n):
        r, f = one.correct_one(raw[i], {k: v[i] for k, v in inputs.items()})
        assert r == pytest.approx(block[i], abs=1e-9)
        assert f == flags[i]
    # After a reset the stateful terms (direction, slope, lag, derivative) start again alike.
    one.reset()
    again = [one.correct_one(raw[i], {k: v[i] for k, v in inputs.items()})[0] for i in range(50)]
    np.testing.assert_allclose(again, block[:50], atol=1e-9)


def test_new_term_kinds_round_trip_a_file_and_need_time():
    from canical.sets import coefficient_file

    cset = coefficient_file.loads(coefficient_file.dumps(extended_set()))
    corrector = Corrector(cset)
    assert set(corrector.required_inputs) == {"temp_c", "supply_v", "time_s"}
    names = [t.describe() for t in cset.terms[-4:]]
    assert cset == extended_set()
    assert names == ["lag(temp_c, τ=140 s)", "d/dt temp_c", "d/dt temp_c", "sign d/dt supply_v"]


def test_a_term_holds_its_kind_object_through_pickle_and_copy():
    """A term holds the registry's kind object; pickled (to a worker) or deep-copied, it holds the
    same one, so terms compare equal and ``spec is`` checks hold on the far side."""
    import copy
    import pickle

    from canical.sets.term_kinds import ALL

    for term in extended_set().terms:
        assert term.spec in ALL and (term.kind, term.feature) == term.spec.key
        for back in (pickle.loads(pickle.dumps(term)), copy.deepcopy(term)):
            assert back.spec is term.spec and back == term and back.to_dict() == term.to_dict()


def test_missing_input_is_named():
    from canical.errors import CanicalError

    with pytest.raises(CanicalError, match="supply_v"):
        Corrector(extended_set()).correct(np.zeros(3), {"temp_c": np.zeros(3), "time_s": np.zeros(3)})


def test_gated_term_is_a_hinge_beyond_the_knee():
    """Scale form: c·(v − ref)·sign(ΔV)·max(|ΔV| − k, 0) — nothing up to the knee, linear beyond."""
    term = term_from_dict({"kind": "channel", "channel": "temp_c", "feature": "gated", "form": "scale",
                           "coefficient": 1.0, "reference": 25.0, "threshold_raw": 1000.0})
    dv = np.array([-3000.0, -1000.0, -10.0, 0.0, 999.0, 1000.0, 1500.0, 4000.0])
    temp = np.full(dv.size, 27.0)
    x = feature_values(term, {"temp_c": temp}, dv + 30.0, dv)
    np.testing.assert_allclose(x * dv, 2.0 * np.sign(dv) * np.maximum(np.abs(dv) - 1000.0, 0.0))
    assert term.describe() == "temp_c × (|ΔV| > 1000 counts)"
    assert Corrector(CoefficientSet("S", "z", 30.0, extended_set().model, terms=(term,))
                     ).required_inputs == ("temp_c",)  # stateless: no time needed


@settings(max_examples=25, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(1.0, 20_000.0), st.sampled_from(["bias", "scale"]))
def test_gated_block_and_per_sample_paths_are_identical(seed, knee, form):
    """A gated term has no state: one sample at a time gives the block's numbers bit for bit."""
    rng = np.random.default_rng(seed)
    n = 300
    raw = rng.normal(0, 8000, n).round()
    raw[:5] = [30.0, 30.0 + knee, 30.0 - knee, 31.0, 29.0]  # at V0 and exactly at the knee
    temp = rng.uniform(-20, 60, n)
    term = {"kind": "channel", "channel": "temp_c", "feature": "gated", "form": form,
            "coefficient": 3e-4 if form == "scale" else 2.0, "reference": 25.0, "threshold_raw": knee}
    cset = CoefficientSet("S", "z", 30.0, extended_set().model, terms=(term_from_dict(term),))
    block, flags = Corrector(cset).correct(raw, {"temp_c": temp})
    one = Corrector(cset)
    pairs = [one.correct_one(raw[i], {"temp_c": temp[i]}) for i in range(n)]
    np.testing.assert_array_equal([p[0] for p in pairs], block)
    np.testing.assert_array_equal([p[1] for p in pairs], flags)


@settings(max_examples=80, deadline=None)
@given(st.integers(0, 2**32 - 1), st.floats(0.01, 50.0), st.integers(1, 5000), st.booleans())
def test_direction_found_a_flip_at_a_time_is_the_tracker_bit_for_bit(seed, threshold, n, plateaus):
    from canical.sets.trackers import direction_state, direction_steps

    rng = np.random.default_rng(seed)
    values = np.cumsum(rng.normal(0, 1, n))
    if plateaus:  # long stretches without a flip, then a step
        values = np.repeat(rng.normal(0, 30, n // 500 + 1), 500)[:n] + rng.normal(0, 0.1, n)
    if n > 10 and seed % 3 == 0:
        values[rng.integers(0, n, 3)] = np.nan
    assert direction_steps(values, threshold).tobytes() == direction_state(values, threshold).tobytes()


@pytest.mark.parametrize("even", [True, False])
def test_vectorised_slope_equals_the_tracker(even):
    from canical.sets.trackers import slope_filter, slope_state

    rng = np.random.default_rng(4)
    n = 20_000
    time_s = np.arange(n) / 1000.0 if even else np.cumsum(rng.uniform(0.0005, 0.0015, n))
    raw = np.cumsum(rng.normal(0, 5, n))
    np.testing.assert_allclose(slope_filter(raw, time_s, 0.5), slope_state(raw, time_s, 0.5),
                               rtol=1e-9, atol=1e-9 * np.abs(np.diff(raw)).max() * 1000)


@pytest.mark.parametrize("block", [1, 7, 4096])
def test_uneven_slope_a_block_at_a_time_is_the_tracker_bit_for_bit(monkeypatch, block):
    from canical.sets import trackers

    monkeypatch.setattr(trackers, "SLOPE_BLOCK", block)
    rng = np.random.default_rng(block)
    n = 10_000
    time_s = np.cumsum(rng.uniform(0.0005, 0.0015, n))
    time_s[100:103] = time_s[100]  # duplicated timestamps: the tracker skips them
    time_s[500] = np.nan
    raw = np.cumsum(rng.normal(0, 5, n))
    raw[2000] = np.nan  # the tracker carries NaN from there on
    whole = trackers.slope_state(raw, time_s, 0.5)
    assert trackers.slope_filter(raw, time_s, 0.5).tobytes() == whole.tobytes()
    assert trackers.slope_filter(raw[:1500], time_s[:1500], 0.5).tobytes() == whole[:1500].tobytes()
    assert np.isfinite(whole[:1500][time_s[:1500] == time_s[:1500]]).all() and np.isnan(whole[-1])
