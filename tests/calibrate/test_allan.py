"""Allan deviation read-outs against synthetic noise whose IEEE 952 terms are known analytically
(tests/support/allan_noise.py builds each term from its defining spectrum).

Tolerances are set from the spread of each estimator over many seeds
(tests/benchmarks/bench_allan.py), not from these seeds: ARW from 10⁵ samples is good to
well under 1% (3% allowed); RRW rests on a few dozen independent long clusters (median error 4%,
one seed in ten beyond 18%, worst of 40 seeds 33%: 40% allowed); the flicker floor of a
finite record is reached from below (median 1% low, worst 12%: 20% allowed).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest
from hypothesis import example, given, settings
from hypothesis import strategies as st
from support.allan_noise import flicker_rate, rate_random_walk, rrw_for_crossover, white_rate

from canical.calibrate.allan import NoiseAnalysis, allan_deviation, noise_terms
from canical.calibrate.noise_records import name_a_rise


@settings(max_examples=10, deadline=None)
@given(seed=st.integers(0, 2**32 - 1), arw=st.floats(0.05, 2.0))
@example(seed=2894, arw=1.0)  # its tail wiggles up at tau 64-200 s: seen at two errors, not at three
def test_white_rate_noise_gives_its_arw_and_nothing_else(seed: int, arw: float) -> None:
    rng = np.random.default_rng(seed)
    fs = 100.0
    curve = allan_deviation([white_rate(rng, 60_000, fs, arw)], fs)
    terms = noise_terms(curve)
    assert terms.arw.resolved
    assert terms.arw.value == pytest.approx(arw, rel=0.03)
    assert terms.arw.low <= terms.arw.value <= terms.arw.high
    # 10 minutes of white noise: the curve falls all the way, no floor and no rise to claim
    for key in ("bias_instability", "rrw"):
        assert not terms[key].resolved, terms[key]
        assert terms[key].note


@pytest.mark.parametrize("seed", range(5))
def test_rate_random_walk_is_read_at_long_tau(seed: int) -> None:
    rng = np.random.default_rng(seed)
    fs, n = 10.0, 200_000  # 5.6 h
    arw = rng.uniform(0.1, 1.0)
    crossover_s = rng.uniform(10.0, 60.0)  # where N²/τ = K²τ/3
    rrw = rrw_for_crossover(arw, crossover_s)
    x = white_rate(rng, n, fs, arw) + rate_random_walk(rng, n, fs, rrw)
    terms = noise_terms(allan_deviation([x], fs))
    assert terms.arw.resolved and terms.arw.value == pytest.approx(arw, rel=0.03)
    assert terms.rrw.resolved and terms.rrw.value == pytest.approx(rrw, rel=0.4)
    assert terms.rrw.tau_s > crossover_s / 2


@pytest.mark.parametrize("seed", range(3))
def test_flicker_floor_gives_the_bias_instability(seed: int) -> None:
    rng = np.random.default_rng(seed)
    fs, n = 10.0, 200_000
    bi = rng.uniform(2.0, 20.0)
    x = white_rate(rng, n, fs, 0.2) + flicker_rate(rng, n, fs, bi)
    terms = noise_terms(allan_deviation([x], fs))
    assert terms.bias_instability.resolved
    assert terms.bias_instability.value == pytest.approx(bi, rel=0.2)
    assert terms.arw.value == pytest.approx(0.2, rel=0.05)


def test_short_records_pool_and_do_not_claim_long_tau_terms() -> None:
    """Zero-rate plateaus of a turntable session: a few 30 s records, pooled per cluster size."""
    rng = np.random.default_rng(7)
    fs = 200.0
    records = [white_rate(rng, 6000, fs, 0.4) + rate_random_walk(rng, 6000, fs, 5.0) for _ in range(4)]
    curve = allan_deviation(records, fs)
    assert curve.records == 4 and curve.duration_s == pytest.approx(120.0)
    assert curve.tau_s[-1] <= 30.0 / 3 + 1e-9  # three independent clusters in the longest record
    assert curve.clusters[0] == 4 * 6000
    terms = noise_terms(curve)
    assert terms.arw.value == pytest.approx(0.4, rel=0.03)
    assert not terms.rrw.resolved and "longer record" in terms.rrw.note
    assert terms.rrw.value > 0  # the bound the data gives


def test_pooled_curve_equals_one_record_cut_in_pieces_up_to_the_lost_joins() -> None:
    rng = np.random.default_rng(3)
    fs = 50.0
    x = white_rate(rng, 30_000, fs, 0.3)
    whole = allan_deviation([x], fs)
    cut = allan_deviation(np.split(x, 3), fs)
    common = np.intersect1d(whole.tau_s, cut.tau_s)
    a = whole.adev[np.isin(whole.tau_s, common)][:5]
    b = cut.adev[np.isin(cut.tau_s, common)][:5]
    np.testing.assert_allclose(a, b, rtol=0.02)


@pytest.mark.parametrize("seed", range(5))
def test_a_rise_over_less_than_a_decade_is_not_claimed_as_rate_random_walk(seed: int) -> None:
    """Short zero-rate records whose rate drifts (the session's temperature, a ramp): the curve
    rises at τ of a second or so, over less than a decade; nothing is claimed there."""
    rng = np.random.default_rng(seed)
    fs = 200.0
    records = []
    for _ in range(4):
        t = np.arange(1000) / fs  # 5 s
        drift = rng.uniform(0.05, 0.2) * rng.choice([-1.0, 1.0]) * t  # deg/s per s: a thermal drift
        records.append(white_rate(rng, t.size, fs, 0.3) + drift)
    terms = noise_terms(allan_deviation(records, fs))
    assert not terms.rrw.resolved
    assert "less than a decade" in terms.rrw.note


def test_the_calibration_names_the_temperature_behind_a_rise() -> None:
    """The demo's turntable session (temperature stepping with the chamber, an effect of it on
    the rate): its report claims no rate random walk from the zero-rate plateaus' seconds, and
    the note names the temperature change behind the rise."""
    from canical.calibration.pipeline import CalibrateOptions, calibrate
    from canical.sim.scenarios import SCENARIOS

    scenario = next(s for s in SCENARIOS if s.name.startswith("temperature bias + scale"))
    result = calibrate(scenario.session(0), CalibrateOptions(extend=False), sensor_id="SIM", axis="z")
    assert isinstance(result.report.allan, NoiseAnalysis)
    rrw = result.report.allan.terms.rrw
    assert not rrw.resolved
    assert "less than a decade" in rrw.note and "temperature spans" in rrw.note, rrw.note


def test_a_rise_is_named_only_when_the_channel_moved() -> None:
    fs = 100.0
    curve = allan_deviation([white_rate(np.random.default_rng(0), 600, fs, 0.3)], fs)
    terms = noise_terms(curve)
    risen = replace(terms.rrw, resolved=False, note="the curve rises between tau 1 and 3 s only")
    analysis = NoiseAnalysis("test", curve, replace(terms, rrw=risen))
    named = name_a_rise(analysis, "temperature", np.array([20.0, 21.5, 23.0]), "°C")
    assert named.terms.rrw.note.endswith("the records' temperature spans 3 °C: likely that drift")
    assert name_a_rise(analysis, "temperature", np.array([20.0, 20.0]), "°C") is analysis
    resolved = replace(analysis, terms=replace(terms, rrw=replace(risen, resolved=True, note="")))
    assert name_a_rise(resolved, "temperature", np.array([20.0, 23.0]), "°C") is resolved


@pytest.mark.parametrize("n", [12, 1000, 200_000])
def test_overlapping_adev_in_blocks_is_allantools(n, monkeypatch):
    import allantools

    from canical.calibrate import allan

    monkeypatch.setattr(allan, "OADEV_BLOCK", 777)
    rng = np.random.default_rng(n)
    record = 0.02 + rng.normal(0, 0.1, n) + np.cumsum(rng.normal(0, 1e-4, n))
    m = np.unique(np.round(np.logspace(0, np.log10(n // 2), 30)).astype(int))
    got_m, devs, ns = allan.overlapping_adev(record, 1000.0, m)
    taus, want, _errs, want_ns = allantools.oadev(record, rate=1000.0, data_type="freq", taus=m / 1000.0)
    np.testing.assert_array_equal(got_m, np.round(taus * 1000.0).astype(int))
    np.testing.assert_allclose(devs, want, rtol=1e-12)
    np.testing.assert_array_equal(ns, want_ns)
