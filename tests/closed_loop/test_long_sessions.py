"""The loop on sessions of hours: a bounded number of blocks, time constants searched beside the
whole session's in every fold, and a bigger base preferred to a channel's form that needs it."""

from dataclasses import replace

import numpy as np
import pytest

from canical.calibrate.model_fit import ModelSpec
from canical.calibration.pipeline import CalibrateOptions, extend_model, fit_base
from canical.closed_loop import blocks as blocks_module
from canical.closed_loop import search
from canical.closed_loop.blocks import BLOCK_S
from canical.closed_loop.candidates import Candidate, group_tau, tau_groups
from canical.closed_loop.findings import Score
from canical.sets.term_kinds import CHANNEL, CHANNEL_OFFSET, TIME, TIME_LINEAR
from canical.sets.terms import Term
from canical.sim import effects as fx
from canical.sim import environment as env
from canical.sim.gyro import GyroModel
from canical.sim.sessions import paper_rates, sweep_session


def lag_session(dwell_s: float = 8.0):
    """The bias follows temp_c through a lag of 60 s while the chamber cycles."""
    rates = np.random.default_rng(3).permutation(np.repeat(paper_rates(), 2))
    gyro = GyroModel(effects=(fx.LaggedTemperatureEffect(tau_s=60.0),))
    return sweep_session(gyro, rates, dwell_s=dwell_s, seed=3, aux={"temp_c": env.temperature_cycle()})


@pytest.fixture(scope="module")
def lagged():
    """The loop's result on the lag session (it finds the lag)."""
    session = lag_session()
    base = fit_base(session, CalibrateOptions())
    return extend_model(session, base, CalibrateOptions())


def test_blocks_stay_within_the_bound(monkeypatch):
    """Plateaus that would make more than MAX_BLOCKS blocks of BLOCK_S are cut into longer ones,
    at most about the bound; the report and the figures say how long they are."""
    session = lag_session(dwell_s=12.0)
    base = fit_base(session, CalibrateOptions())
    usual = extend_model(session, base, CalibrateOptions()).blocks
    assert usual.block_s == BLOCK_S and usual.label == "2 s blocks"
    bound = len(usual) // 3
    monkeypatch.setattr(blocks_module, "MAX_BLOCKS", bound)
    long = extend_model(session, base, CalibrateOptions()).blocks
    assert long.block_s > 2.5 * BLOCK_S
    assert len(long) <= bound * 1.05
    assert long.label == f"{long.block_s:.2g} s blocks"


def test_report_names_the_blocks_it_measured_on(monkeypatch):
    from canical.calibration.pipeline import calibrate
    from canical.report.markdown import render

    session = lag_session()
    monkeypatch.setattr(blocks_module, "MAX_BLOCKS", 100)
    result = calibrate(session, CalibrateOptions(), sensor_id="S", axis="z")
    loop = result.report.closed_loop
    assert loop is not None and loop.block_s > BLOCK_S
    label = f"{loop.block_s:.2g} s blocks"
    assert label in loop.method and label in render(result.report, [])
    assert "2 s blocks" not in render(result.report, [])


def test_a_folds_time_constant_is_searched_beside_the_sessions(lagged):
    """Started next to the whole session's τ, a fold's search finds what a search of the whole grid
    finds; started where the least of its points is at an end (on the slope a grid step above the
    minimum), it goes on past it and finds it too."""
    fit = lagged.fit
    s = search.Structure(lagged.structure.spec, lagged.structure.knots, lagged.structure.scale,
                         lagged.structure.span, fit.terms)
    group = next(g for g in tau_groups(fit.terms) if g[1] == "temp_c")
    near = group_tau(fit.terms, group)
    assert near is not None and 20.0 < near < 200.0
    folds = search.plateau_folds(lagged.blocks)
    duration = float(lagged.blocks.time_s.max())
    for held in folds[:2]:
        train = lagged.blocks.take(~held)
        tau_search = search._TauSearch(train, s, duration, group, search._mean_sensitivity(train.points),
                                       search._unshifted_design(train, s))
        whole_grid = tau_search.best()
        assert tau_search.best(near) == pytest.approx(whole_grid, rel=0.02)
        grid = tau_search.grid()
        on_the_slope = whole_grid * grid[1] / grid[0]
        assert tau_search.best(on_the_slope) == pytest.approx(whole_grid, rel=0.02)


def test_held_out_errors_kept_by_the_scorer(lagged):
    """The loop's before and after figures are the errors its scores were made of."""
    scorer = search.Scorer(lagged.blocks, search.plateau_folds(lagged.blocks),
                           float(lagged.blocks.time_s.max()))
    errors = scorer.errors(lagged.structure)
    assert np.isfinite(errors).sum() > 0.5 * errors.size
    assert search.rms(errors) == scorer.held_rms(lagged.structure)


class _Scores:
    """A scorer whose scores are given: what :func:`search._judge` reads of one."""

    def __init__(self, scores: dict[str, Score], n_plateaus: int = 60) -> None:
        self.scores, self.n_plateaus = scores, n_plateaus

    def score(self, s: search.Structure) -> Score:
        terms = ",".join(t.channel or "time" for t in s.terms) or "base"
        return self.scores[f"{terms}/{s.spec.n_segments}"]


SMALL = search.Structure(ModelSpec(n_segments=3, order=3), np.array([-1.0, 1.0]), 10.0, (-10.0, 10.0))
BIGGER = replace(SMALL, spec=ModelSpec(n_segments=4, order=3), knots=np.array([-1.0, 0.0, 1.0]))
CHANNEL_LEVEL = Candidate("channel:temp_c", CHANNEL, "temp_c",
                          (Term.of(CHANNEL_OFFSET, "bias", 0.0, channel="temp_c"),))
DRIFT = Candidate("time:linear-drift", TIME, None, (Term.of(TIME_LINEAR, "bias", 0.0),))
BAR = search._Bar(min_gain=0.1, alpha=0.01)
#: A round where a channel's level passes just ahead of a fourth segment, and a drift behind.
ROUND = [(0.0099, "channel:temp_c", CHANNEL_LEVEL), (0.0100, "capacity", BIGGER),
         (0.0120, "time:linear-drift", DRIFT)]


def scorer(on_bigger_base: Score) -> _Scores:
    """The bigger base alone at 0.010 deg/s; with the channel's level, ``on_bigger_base``."""
    return _Scores({"base/4": Score(0.010, 0.5, 17), "temp_c/4": on_bigger_base})


def test_a_channel_form_must_also_pass_on_the_bigger_base():
    """A channel's form ahead of a bigger base is taken only where it passes on that base too."""
    gains_little = scorer(Score(0.0098, 0.49, 18))
    assert search._base_before_channel(gains_little, ROUND, BAR) == ("capacity", BIGGER)
    still_there = scorer(Score(0.0030, 0.02, 18))
    assert search._base_before_channel(still_there, ROUND, BAR) == ("channel:temp_c", CHANNEL_LEVEL)


def test_other_picks_are_left_as_they_are():
    """A pick of time, a channel with no bigger base passing, a bigger base: taken as they are."""
    gains_little = scorer(Score(0.0098, 0.49, 18))
    assert search._base_before_channel(gains_little, ROUND[2:], BAR) == ("time:linear-drift", DRIFT)
    assert search._base_before_channel(gains_little, ROUND[::2], BAR) == ("channel:temp_c", CHANNEL_LEVEL)
    assert search._base_before_channel(gains_little, ROUND[1:], BAR) == ("capacity", BIGGER)


@pytest.mark.parametrize("vertex", [-0.7, -0.2, 0.0, 0.33, 0.99])
def test_parabola_vertex_is_exact_on_a_parabola(vertex):
    x = np.array([-1.0, 0.0, 1.0]) * 0.4 + 0.1
    y = 3.0 * (x - (0.1 + 0.4 * vertex)) ** 2 + 7.0
    assert search.parabola_vertex(x, y) == pytest.approx(0.1 + 0.4 * vertex, abs=1e-12)


def test_parabola_vertex_stays_within_its_points():
    x = np.array([1.0, 2.0, 3.0])
    assert search.parabola_vertex(x, np.array([5.0, 5.0, 5.0])) == 2.0  # level: the middle
    assert 1.0 <= search.parabola_vertex(x, np.array([1.0, 1.0 - 1e-15, 9.0])) <= 3.0


def test_parabola_vertex_on_points_unevenly_spaced():
    x = np.array([3.0, 2.0, 0.0])  # in order along x, downward, spaced 1 then 2
    assert search.parabola_vertex(x, 0.7 * (x - 1.6) ** 2 + 4.0) == pytest.approx(1.6, abs=1e-12)


class _Bowl:
    """An RSS with its least at ``at`` (log τ), counting the points it was taken at."""

    def __init__(self, at: float) -> None:
        self.at, self.taken = at, 0

    def rss(self, x: float) -> float:
        self.taken += 1
        return (x - self.at) ** 2


@pytest.mark.parametrize("at", [1.05, 1.3, 2.9, -0.4])
def test_a_search_past_its_points_brackets_the_least_in_a_few_steps(at):
    bowl = _Bowl(at)
    up = at > 0.9
    x_in, x = (0.8, 0.9) if up else (0.1, 0.0)
    start = (x_in, x), (bowl.rss(x_in), bowl.rss(x))
    bowl.taken = 0
    found = search._TauSearch.beyond(bowl, start, bound=5.0 if up else -5.0)  # type: ignore[arg-type]
    assert found == pytest.approx(at, abs=1e-9)  # a parabola's vertex on a parabola
    assert bowl.taken <= 2 + int(np.log2(abs(at) / 0.1 + 1))


def test_a_search_past_its_points_stops_at_the_grids_end():
    bowl = _Bowl(9.0)
    assert search._TauSearch.beyond(bowl, ((0.8, 0.9), (bowl.rss(0.8), bowl.rss(0.9))), bound=2.0) == 2.0
    assert search._TauSearch.beyond(bowl, ((2.4, 2.5), (bowl.rss(2.4), bowl.rss(2.5))), bound=2.0) == 2.0
