"""A stream corrected block by block is, bit for bit, the stream corrected at once.

Why: ``canical apply`` corrects a long file a block at a time; the stateful terms (direction,
slope, lag, derivative, a channel's direction) carry their state across the blocks' edges.
"""

from __future__ import annotations

import itertools

import numpy as np
from hypothesis import given, settings
from hypothesis import strategies as st
from test_terms import extended_set

from canical.sets.corrector import Corrector


def stream(seed: int, n: int) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    rng = np.random.default_rng(seed)
    raw = np.cumsum(rng.normal(0, 300, n)) + rng.normal(0, 30, n)
    inputs = {"temp_c": 25 + np.cumsum(rng.normal(0, 0.3, n)), "supply_v": rng.uniform(4.5, 5.5, n),
              "time_s": np.cumsum(rng.uniform(0.001, 0.05, n))}
    return raw, inputs


@settings(max_examples=60, deadline=None)
@given(st.integers(0, 2**32 - 1), st.lists(st.integers(0, 800), max_size=12))
def test_any_split_gives_the_same_bits(seed, cuts):
    raw, inputs = stream(seed, 800)
    whole, whole_flags = Corrector(extended_set()).correct(raw, inputs)
    corrector = Corrector(extended_set())
    edges = [0, *sorted(cuts), len(raw)]
    parts = [corrector.correct_next(raw[a:b], {k: v[a:b] for k, v in inputs.items()})
             for a, b in itertools.pairwise(edges)]
    rate = np.concatenate([p[0] for p in parts])
    flags = np.concatenate([p[1] for p in parts])
    assert rate.tobytes() == whole.tobytes()
    assert np.array_equal(flags, whole_flags)


def test_reset_starts_a_new_stream():
    raw, inputs = stream(3, 300)
    corrector = Corrector(extended_set())
    first = corrector.correct_next(raw, inputs)[0]
    corrector.correct_next(raw[:100], {k: v[:100] for k, v in inputs.items()})
    corrector.reset()
    assert corrector.correct_next(raw, inputs)[0].tobytes() == first.tobytes()


def test_a_piecewise_model_is_elementwise():
    assert Corrector(extended_set()).elementwise_model
