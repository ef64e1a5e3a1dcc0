"""Plateau detection: transitions and settling are left out, repeated sweeps stay separate."""

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from canical.calibrate.plateaus import detect_plateaus, plateau_means, ranged_medians
from canical.errors import CanicalError
from canical.sim.rate_table import step_profile
from canical.sim.table_recording import TableBehaviour, record_table


def test_plateaus_found_at_each_rate_with_transitions_excluded():
    rates = np.array([0.0, 10.0, -20.0, 5.0])
    t, w = step_profile(rates, dwell_s=5.0, fs_hz=100.0, accel_dps2=50.0)
    p = detect_plateaus(t, w)
    assert p.count == 4
    np.testing.assert_allclose(p.rate_dps, rates)
    # No used sample is on a ramp, and each plateau drops its settling start.
    used = p.label >= 0
    assert np.all(np.isin(w[used], rates))
    assert p.n_transition > 0 and p.n_settling > 0
    assert p.n_used + p.n_transition + p.n_settling == len(t)
    for a in p.start:
        assert w[a - 1] == w[a]  # settling samples before the first used one are on the plateau


def test_repeated_sweeps_give_separate_plateaus():
    rates = np.array([0.0, 10.0, 0.0, 10.0])
    t, w = step_profile(rates, dwell_s=3.0, fs_hz=100.0)
    p = detect_plateaus(t, w)
    assert p.count == 4
    assert len(set(p.start)) == 4


def test_short_runs_are_not_plateaus():
    t = np.arange(300) / 100.0
    w = np.concatenate([np.zeros(200), np.full(50, 5.0), np.zeros(50)])
    p = detect_plateaus(t, w, min_duration_s=1.0)
    np.testing.assert_allclose(p.rate_dps, [0.0])


def test_noisy_reference_within_tolerance_is_one_plateau():
    rng = np.random.default_rng(0)
    t = np.arange(1000) / 100.0
    w = 30.0 + 0.005 * rng.standard_normal(1000)
    p = detect_plateaus(t, w, rate_tol=0.05)
    assert p.count == 1
    assert abs(p.rate_dps[0] - 30.0) < 0.01


def test_plateau_means_match_numpy():
    t, w = step_profile(np.array([0.0, 7.0]), dwell_s=4.0, fs_hz=50.0)
    p = detect_plateaus(t, w)
    values = np.sin(t)
    expected = [values[a:b].mean() for a, b in zip(p.start, p.stop, strict=True)]
    np.testing.assert_allclose(plateau_means(values, p), expected)


# --- Recordings as real tables make them (canical.sim.table_recording) -------------------------

RATES = np.array([0.0, 3.0, 6.0, -9.0, 20.0, 0.0, -3.0])


def _record(behaviour: TableBehaviour, *, seed: int = 0, dwell_s: float = 4.0, fs_hz: float = 100.0):
    rec = record_table(RATES, dwell_s=dwell_s, fs_hz=fs_hz, behaviour=behaviour,
                       rng=np.random.default_rng(seed))
    keep = rec.kept
    return rec, rec.time_s[keep], rec.ref_dps[keep], rec.settled[keep]


def _on_ramp(rec, t_used: np.ndarray, label_used: np.ndarray) -> int:
    """Used rows whose tick lies outside the scheduled plateau they were given (truth known).

    A plateau spans [end of its rate change, start of the next] inclusive: at both instants
    the table is at the plateau's rate.
    """
    s = rec.schedule
    eps = 1e-9
    return int(np.sum((t_used < s.end[label_used] - eps) | (t_used > s.stop[label_used] + eps)))


def _check_all_found(behaviour: TableBehaviour, seed: int = 0, **kw):
    rec, t, ref, _ = _record(behaviour, seed=seed)
    p = detect_plateaus(t, ref, **kw)
    assert p.count == RATES.size, p.describe()
    np.testing.assert_allclose(p.rate_dps, RATES, atol=max(0.01, 5 * float(np.max(p.rate_uncertainty()))))
    used = p.label >= 0
    assert _on_ramp(rec, t[used], p.label[used]) == 0
    return rec, p


@pytest.mark.parametrize("accel", [1.0, 3.0, 10.0, 100.0])
def test_slow_ramps_are_not_plateaus(accel):
    """The landed detector saw a 1 deg/s² sweep as one plateau: steadiness is judged over a window."""
    _check_all_found(TableBehaviour(accel_dps2=accel))


def test_s_curve_and_ringing_are_left_out():
    _check_all_found(TableBehaviour(accel_dps2=5.0, jerk_dps3=5.0, overshoot=0.1, reference="measured"))


@pytest.mark.parametrize("jitter", [0.01, 0.02, 0.05])
def test_measured_reference_noise_is_estimated_and_sets_the_tolerance(jitter):
    _, p = _check_all_found(TableBehaviour(accel_dps2=10.0, reference="measured", jitter_dps=jitter))
    assert p.ref_noise_dps == pytest.approx(jitter, rel=0.25)
    assert p.rate_tol_dps > 2 * jitter / np.sqrt(p.window_s * 100.0)
    assert p.describe().reference_noise_dps == p.ref_noise_dps


@pytest.mark.parametrize("asynchronous", [False, True])
def test_held_and_late_reference_ends_guarded(asynchronous):
    """A 10 Hz reference shows the next ramp up to 0.1 s late (plus its latency): that much is cut."""
    b = TableBehaviour(accel_dps2=10.0, ref_rate_hz=10.0, asynchronous=asynchronous, ref_latency_s=0.05)
    _, p = _check_all_found(b, latency_s=0.05)
    assert p.update_s == pytest.approx(0.1, rel=0.05)
    assert p.end_guard_s == pytest.approx(0.15, rel=0.05)


def test_lost_bursts_duplicated_timestamps_and_uneven_sampling():
    _, t, ref, _ = _record(TableBehaviour(accel_dps2=10.0, loss_fraction=0.05, loss_burst_s=0.3))
    rng = np.random.default_rng(1)
    t = t + rng.uniform(-0.003, 0.003, t.size)  # uneven sampling
    t = np.sort(t)
    dup = rng.choice(t.size - 1, 50, replace=False)
    t[dup + 1] = t[dup]  # duplicated timestamps
    p = detect_plateaus(t, ref)
    assert p.count == RATES.size
    np.testing.assert_allclose(p.rate_dps, RATES, atol=1e-9)


def test_an_outlier_in_the_reference_does_not_split_a_plateau():
    t = np.arange(1000) / 100.0
    w = np.full(1000, 30.0)
    w[500] = 35.0
    p = detect_plateaus(t, w)
    assert p.count == 1
    assert p.rate_dps[0] == pytest.approx(30.0)


def test_settled_flag_narrows_but_never_overrides_a_moving_reference():
    rec, t, ref, settled = _record(TableBehaviour(accel_dps2=3.0, settled_flag=True))
    always = detect_plateaus(t, ref, settled=np.ones(t.size, dtype=bool))
    used = always.label >= 0
    assert always.count == RATES.size and _on_ramp(rec, t[used], always.label[used]) == 0
    # A table that says "not settled" for the first 2 s of every plateau: those rows are not used.
    late = settled.copy()
    k = np.searchsorted(rec.schedule.end, t, side="right") - 1
    late &= t >= rec.schedule.end[np.clip(k, 0, None)] + 2.0
    p = detect_plateaus(t, ref, settled=late)
    assert p.count == RATES.size
    assert not np.any((p.label >= 0) & ~late)
    assert p.n_not_settled > 0


def test_time_going_backwards_names_the_first_bad_row():
    t = np.arange(100) / 100.0
    t[40] = 0.1
    with pytest.raises(CanicalError, match=r"goes backwards at row 41 \(0\.1 s after 0\.39 s\)"):
        detect_plateaus(t, np.zeros(100))


behaviours = st.builds(
    TableBehaviour,
    accel_dps2=st.sampled_from([None, 1.0, 2.0, 5.0, 20.0, 100.0]),
    overshoot=st.sampled_from([0.0, 0.05, 0.1]),
    reference=st.sampled_from(["commanded", "measured"]),
    jitter_dps=st.floats(0.0, 0.05),
    encoder_lsb_dps=st.sampled_from([0.0, 0.001, 0.005]),
    ref_rate_hz=st.sampled_from([None, 10.0, 25.0]),
    asynchronous=st.booleans(),
    ref_latency_s=st.floats(0.0, 0.05),
    loss_fraction=st.floats(0.0, 0.05),
)


@settings(max_examples=25, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(behaviours, st.integers(0, 10_000))
def test_every_plateau_found_and_no_ramp_row_used_on_any_table(behaviour, seed):
    _check_all_found(behaviour, seed=seed, latency_s=behaviour.ref_latency_s)


@given(st.data())
@settings(max_examples=200, deadline=None)
def test_ranged_medians_equal_one_median_per_range(data) -> None:
    """The vectorised window medians are exactly np.median of each range (NaN when empty)."""
    n = data.draw(st.integers(1, 300))
    x = np.asarray(data.draw(st.lists(st.floats(-1e3, 1e3, allow_nan=False), min_size=n, max_size=n)))
    starts = np.asarray(data.draw(st.lists(st.integers(0, n), min_size=1, max_size=40)))
    stops = np.asarray([data.draw(st.integers(0, n)) for _ in starts])
    want = np.array([np.median(x[a:b]) if b > a else np.nan for a, b in zip(starts, stops, strict=True)])
    assert np.array_equal(ranged_medians(x, starts, stops), want, equal_nan=True)


@pytest.mark.parametrize(("n", "reach", "block"),
                         [(1000, 50, 64), (70_000, 1000, 1 << 14), (20, 19, 4), (500, 7, 500)])
def test_near_correlation_is_the_full_correlation_near_zero_lag(n, reach, block):
    from scipy.signal import correlate, correlation_lags

    from canical.calibrate.plateaus import near_correlation

    rng = np.random.default_rng(n)
    x = rng.normal(size=n)
    y = np.roll(x, 3) + rng.normal(size=n) * 0.1
    full = correlate(x, y, mode="full", method="fft")
    near = np.abs(correlation_lags(n, n)) <= reach
    np.testing.assert_allclose(near_correlation(x, y, reach, block), full[near], rtol=0,
                               atol=1e-12 * np.abs(full).max())


@settings(max_examples=200, deadline=None)
@given(st.integers(1, 300), st.integers(1, 300), st.integers(0, 2**31))
def test_full_correlation_is_scipys(m, p, seed):
    from scipy.signal import correlate

    from canical.calibrate.plateaus import full_correlation

    rng = np.random.default_rng(seed)
    x, y = rng.normal(size=m), rng.normal(size=p)
    want = correlate(x, y, mode="full", method="direct")
    np.testing.assert_allclose(full_correlation(x, y), want, rtol=0, atol=1e-12 * (np.abs(want).max() + 1))
