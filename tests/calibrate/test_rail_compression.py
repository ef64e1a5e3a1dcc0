"""A sensor that compresses near its rail: the size chosen follows the bend (issue 32, the rail).

Orders above 3 are a second round (:data:`canical.calibrate.model_selection.HIGH_ORDERS`),
offered only for a sensor that reached its rail inside the table's range or bends toward one
(:func:`canical.calibrate.model_selection.end_compression`), and taken only where they clearly
lower the held-out error.
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from support.rail_truth import error_of, hindsight

from canical.calibrate.fit_points import FitPoints
from canical.calibrate.model_fit import ModelSpec
from canical.calibrate.model_selection import (
    END_COMPRESSION,
    HIGH_ORDERS,
    ORDER_CHOICES,
    SEGMENT_CHOICES,
    _candidates,
    _clearly_better,
    end_compression,
    select_model,
)
from canical.calibration.pipeline import CalibrateOptions, fit_base
from canical.models.kinds import SEGMENTED_INVERSE
from canical.sim.compression import draw_compressing
from canical.sim.gyro import GyroModel
from canical.sim.sessions import paper_session

START = ModelSpec(SEGMENTED_INVERSE, 4, 2, 0)


@pytest.mark.parametrize("bend", [(1.02, 1.3), (1.3, 2.0)], ids=["hard knee", "gentle bend"])
def test_a_compressing_sensor_ends_near_a_polynomial_fitted_with_hindsight(bend):
    chosen, low = [], []
    for seed in range(2000, 2005):
        case = draw_compressing(seed, asymptote=bend)
        base = fit_base(case.session, CalibrateOptions(extend=False))
        assert base.left_out, f"seed {seed}: the plateaus beyond the rail were fitted"
        chosen.append(error_of(case, base, base.fitted.spec))
        low.append(error_of(case, base, select_model(base.points, START)[0]))
        assert chosen[-1] <= 1.2 * hindsight(case, base), f"seed {seed}"
    assert np.median(chosen) <= 0.7 * np.median(low), (chosen, low)


@pytest.mark.parametrize("seed", range(4))
def test_a_sensor_that_never_reached_its_rail_is_offered_orders_up_to_3(seed):
    base = fit_base(paper_session(GyroModel(), seed=seed), CalibrateOptions(extend=False))
    assert not base.left_out
    assert base.candidates and max(c.order for c in base.candidates) == 3


def test_a_sensor_bending_hard_before_a_rail_it_never_reaches_gets_the_higher_order():
    """Hard knees whose output stays below the rail over the whole table (nothing left out): the
    bend shows, and each ends within 1.2x of the hindsight polynomial, where orders up to 3 alone
    miss at least one of them."""
    unclipped = []
    for seed in range(3000, 3030):
        case = draw_compressing(seed, asymptote=(1.02, 1.3))
        base = fit_base(case.session, CalibrateOptions(extend=False))
        if base.left_out:
            continue
        assert end_compression(base.points) >= END_COMPRESSION, f"seed {seed}"
        hind = hindsight(case, base)
        unclipped.append(error_of(case, base, select_model(base.points, START)[0]) / hind)
        assert error_of(case, base, base.fitted.spec) <= 1.2 * hind, f"seed {seed}"
    assert len(unclipped) >= 5 and max(unclipped) > 1.2, unclipped


@pytest.mark.parametrize("seed", range(3))
def test_the_paper_sensor_shows_no_bend_toward_a_rail(seed):
    """Its ends are less sensitive than its middle, but far less so than a knee's."""
    points = fit_base(paper_session(GyroModel(), seed=seed), CalibrateOptions(extend=False)).points
    assert 0.0 < end_compression(points) < 0.6 * END_COMPRESSION


def test_the_bend_is_read_at_either_end_and_needs_a_middle():
    rate = np.array([-60.0, -57.0, -30.0, 0.0, 30.0, 57.0, 60.0])
    dv = 100.0 * rate
    dv[-1] = dv[-2] + 100.0 * 3.0 * 0.5  # the last step half as sensitive
    points = FitPoints(rate, dv, np.ones(7), np.ones(7))
    assert end_compression(points) == pytest.approx(0.5)
    flipped = FitPoints(-rate, dv, np.ones(7), np.ones(7))  # a sensor of negative sensitivity
    assert end_compression(flipped) == pytest.approx(0.5)
    few = FitPoints(rate[[0, 1, 5, 6]], dv[[0, 1, 5, 6]], np.ones(4), np.ones(4))
    assert end_compression(few) == 0.0


def test_a_sensor_at_its_rail_is_offered_the_second_round():
    base = fit_base(draw_compressing(2000).session, CalibrateOptions(extend=False))
    assert base.left_out
    assert {c.order for c in base.candidates} == {1, 2, 3, *HIGH_ORDERS}


def test_the_second_round_needs_the_typical_fold_to_improve():
    """Overall clearly lower is not enough when one fold carries it (a drifting bias)."""
    session = draw_compressing(1000, asymptote=(1.02, 1.3)).session  # a hard knee: the round wins
    points = fit_base(session, CalibrateOptions(extend=False)).points
    first = _candidates(points, START, SEGMENT_CHOICES, ORDER_CHOICES)
    higher = _candidates(points, START, SEGMENT_CHOICES, HIGH_ORDERS)
    assert _clearly_better(higher, first)
    best = min(first, key=lambda c: c.held_out.rms_dps)
    folds = best.held_out.fold_rms_dps
    one_fold = replace(best, held_out=replace(best.held_out, rms_dps=best.held_out.rms_dps * 0.5,
                                              fold_rms_dps=(folds[0] * 0.1, *folds[1:])))
    assert not _clearly_better([one_fold], first)


def test_a_given_order_is_kept():
    session = draw_compressing(2000).session
    spec = fit_base(session, CalibrateOptions(extend=False, order=3)).fitted.spec
    assert spec.order == 3 and 3 not in HIGH_ORDERS
