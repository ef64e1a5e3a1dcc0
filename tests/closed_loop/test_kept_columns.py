"""The loop keeps what it derives from a set of blocks (a fold's subset, a term's column) and hands
the same back: a τ search fits the structure again at every τ it tries, and every structure scored
meets the same folds, so these were computed again thousands of times."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from canical.calibration.pipeline import CalibrateOptions, calibrate
from canical.closed_loop.candidates import KEPT_COLUMNS, feature, shift_column, shift_columns
from canical.closed_loop.search import plateau_folds
from canical.sim.scenarios import SCENARIOS


@pytest.fixture(scope="module")
def loop_blocks():
    scenario = next(s for s in SCENARIOS if s.name.startswith("thermal transient while"))
    return calibrate(scenario.session(seed=2, dwell_s=6.0), CalibrateOptions(), sensor_id="S",
                     axis="z").loop


def test_a_folds_blocks_are_the_same_object_for_the_same_mask(loop_blocks):
    blocks = loop_blocks.blocks
    held = plateau_folds(blocks)[0]
    assert blocks.take(~held) is blocks.take(~held.copy())
    assert blocks.take(held) is not blocks.take(~held)
    np.testing.assert_array_equal(blocks.take(held).points.rate, blocks.points.rate[held])


def test_a_kept_column_is_the_terms_feature_and_cannot_be_changed(loop_blocks):
    blocks = loop_blocks.blocks.take(~plateau_folds(loop_blocks.blocks)[1])
    for cand in loop_blocks.candidates:
        for term in cand.terms:
            column = shift_column(term, blocks)
            fresh = feature(term, blocks) * (blocks.points.dv if term.form == "scale" else 1.0)
            np.testing.assert_array_equal(column, fresh)
            assert shift_column(term, blocks) is column  # kept, whatever its coefficient
            assert not column.flags.writeable
    stacked = shift_columns(loop_blocks.candidates[0].terms, blocks)
    assert stacked.flags.writeable  # a stack of kept columns is the caller's own


def test_the_kept_columns_are_bounded(loop_blocks):
    blocks = loop_blocks.blocks
    lag = next(c for c in loop_blocks.candidates if c.name == "lag(temp_c)").terms[0]
    for k in range(KEPT_COLUMNS + 10):
        shift_column(replace(lag, params=replace(lag.params, tau_s=5.0 + k)), blocks)
    assert len(blocks.columns) <= KEPT_COLUMNS


def test_blocks_made_by_replace_keep_nothing_of_the_originals(loop_blocks):
    """Other channels, other columns: a replaced copy starts with its own empty caches."""
    blocks = loop_blocks.blocks
    shift_column(loop_blocks.candidates[0].terms[0], blocks)
    blocks.take(plateau_folds(blocks)[0])
    copy = replace(blocks, aux={**blocks.aux})
    assert copy.columns == {} and copy.subsets == {}
    assert copy.columns is not blocks.columns
