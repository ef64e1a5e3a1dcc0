"""Effect terms at run time: validation, trackers, and block and per-sample paths agreeing."""

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canical.coefficients import CoefficientSet, piecewise_model_dict
from canical.corrector import Corrector
from canical.piecewise import PiecewisePoly
from canical.terms import DirectionTracker, SlopeTracker, term_from_dict


def test_direction_tracker_has_hysteresis():
    t = DirectionTracker(10.0)
    seq = [0, 5, 11, 8, 15, 4, 3, 20, 9]
    states = [t.update(v) for v in seq]
    assert states == [0, 0, 1, 1, 1, -1, -1, 1, -1]


def test_slope_tracker_converges_to_the_ramp_slope():
    t = SlopeTracker(0.1)
    out = [t.update(3.0 * k * 0.01, k * 0.01) for k in range(500)]
    assert out[-1] == pytest.approx(3.0)


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
)


def extended_set() -> CoefficientSet:
    poly = PiecewisePoly(np.array([-3000.0, 5000.0]),
                         np.array([[0.1, 60.0, 1.0], [0.0, 60.5, 0.0], [0.2, 59.0, -1.0]]), 24000.0,
                         (-24000.0, 24000.0))
    model = piecewise_model_dict("segmented-inverse", poly, 30.0, smoothness=None,
                                 segment_points_dps=[-7.0, 12.0])
    return CoefficientSet("S", "z", 30.0, model, terms=ALL_TERMS)


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


def test_missing_input_is_named():
    from canical.errors import CanicalError

    with pytest.raises(CanicalError, match="supply_v"):
        Corrector(extended_set()).correct(np.zeros(3), {"temp_c": np.zeros(3), "time_s": np.zeros(3)})
