"""The carried error less the standstills' own noise (``fleet replay``): on synthetic standstills
with a known bias and known noise, white or coloured, the sum of m² less each stop's estimated
mean variance recovers the bias² within its stated uncertainty, where m² alone is biased by the
noise of the mean; the naive variance over n is not that noise once the noise is coloured; the
figure is carried through ``Generation.plus`` and written in ``replay.csv``."""

from __future__ import annotations

import math

import numpy as np
import pytest
from scipy.signal import lfilter

from canical.fleet.replay import Generation, VehicleResult, _Tally, vehicles_csv
from canical.fleet.stop_noise import MeanNoise, StopSeconds

HZ, STOP_S, STOPS = 100.0, 15.0, 400
BIAS = 0.001  # deg/s: below the noise of a 15 s mean (0.05/√1500 = 0.0013 white alone)


def white(rng: np.random.Generator, n: int) -> np.ndarray:
    return 0.05 * rng.standard_normal(n)


def coloured(rng: np.random.Generator, n: int) -> np.ndarray:
    """White noise, low-passed noise (50 ms: its mean is noisier than σ²/n says) and an idle tone
    of 22-30 Hz (0.15 deg/s: its samples are large, its mean nearly nothing), as a stop's."""
    t = np.arange(n) / HZ
    phi = math.exp(-1 / (HZ * 0.05))
    red = lfilter([math.sqrt(1 - phi * phi)], [1, -phi], 0.01 * rng.standard_normal(n))
    tone = 0.15 * np.sin(2 * np.pi * rng.uniform(22, 30) * t + rng.uniform(0, 2 * np.pi))
    return np.asarray(red + tone + white(rng, n))


def stops(noise: str, trend: float = 0.0, seed: int = 1) -> tuple[float, MeanNoise, float]:
    """Over :data:`STOPS` standstills of bias :data:`BIAS` (plus a linear trend of ``trend`` over
    each, its mean still BIAS): Σm², the estimate's sums, and Σ naive s²/n."""
    rng = np.random.default_rng(seed)
    n = int(STOP_S * HZ)
    t = np.arange(n) / HZ
    m_sq, naive, got = 0.0, 0.0, MeanNoise(0.0, 0.0)
    for _ in range(STOPS):
        x = BIAS + trend * (t / STOP_S - 0.5) + (white(rng, n) if noise == "white" else coloured(rng, n))
        seconds = StopSeconds()
        seconds.add(t, x)
        m = float(x.mean())
        m_sq += m * m
        naive += float(np.var(x, ddof=1)) / n
        got = got.plus(seconds.noise(m))
    return m_sq, got, naive


@pytest.mark.parametrize("noise", ["white", "coloured"])
def test_less_its_noise_the_carried_square_is_the_bias_square(noise: str) -> None:
    m_sq, got, naive = stops(noise)
    truth, sd = STOPS * BIAS**2, math.sqrt(got.less_noise_var)
    assert abs(m_sq - got.variance - truth) < 3 * sd  # unbiased, within its uncertainty
    assert m_sq - truth > 5 * sd  # m² alone: biased by the noise of the mean
    if noise == "coloured":  # the naive variance over n is not the mean's noise here
        assert abs(m_sq - naive - truth) > 5 * sd


def test_a_trend_within_the_stop_is_error_not_noise() -> None:
    """A stop warming while it lasts (its bias moving 0.02 deg/s over it): about a line, the
    trend is not taken for noise."""
    m_sq, got, _ = stops("white", trend=0.02)
    assert abs(m_sq - got.variance - STOPS * BIAS**2) < 3 * math.sqrt(got.less_noise_var)


def test_any_cut_into_blocks_gives_the_same_estimate() -> None:
    rng = np.random.default_rng(3)
    t = 40.0 + np.arange(1234) / HZ
    x = coloured(rng, len(t))
    whole = StopSeconds(40.0)
    whole.add(t, x)
    for cuts in ([617], [1, 2, 3, 150, 1233], list(range(0, 1234, 37))):
        pieces = StopSeconds(40.0)
        for a, b in zip([0, *cuts], [*cuts, len(t)], strict=True):
            pieces.add(t[a:b], x[a:b])
        assert pieces.noise(0.01).variance == pytest.approx(whole.noise(0.01).variance, rel=1e-12)


def test_too_short_a_stop_estimates_nothing() -> None:
    seconds = StopSeconds()
    seconds.add(np.arange(150) / HZ, np.ones(150))
    assert seconds.noise(1.0) == MeanNoise(0.0, 0.0)


def test_the_replay_tally_removes_each_stops_noise() -> None:
    """Through the replay's tally: a power-on's first stop left out, the others' carried error
    (the output less the bias as the stop began) less their noise is the bias they carried."""
    rng = np.random.default_rng(5)
    tally, clock = _Tally(), 0.0
    for k in range(200):  # drive 10 s, stop 15 s, one power-on
        n_drive, n_stop = int(10 * HZ), int(STOP_S * HZ)
        t = clock + np.arange(n_drive + n_stop) / HZ
        stop = np.r_[np.zeros(n_drive, bool), np.ones(n_stop, bool)]
        applied = 0.1 * k  # the bias the tracker applies; the output carries BIAS more at the stop
        bias = np.full(len(t), applied)
        err = np.where(stop, BIAS, 0.0) + coloured(rng, len(t))
        for a, b in ((0, 1700), (1700, len(t))):  # two blocks, cut inside the stop
            tally.block(t[a:b], stop[a:b], err[a:b], None, bias[a:b])
        clock = float(t[-1]) + 1 / HZ
    g = tally.result()
    assert g.stops == 199
    assert abs(g.carried_sq - g.carried_noise_sq - g.stops * BIAS**2) < 3 * math.sqrt(g.less_noise_var)
    assert g.carried_sq - g.stops * BIAS**2 > 3 * math.sqrt(g.less_noise_var)
    assert g.carried_less_noise_dps == pytest.approx(BIAS, rel=0.5)
    assert g.carried_less_noise_sd_dps > 0


def generation(k: float) -> Generation:
    return Generation(stops=4, error_sq=k, heading_sq=k, drives=1, carried_sq=4e-6 * k,
                      carried_noise_sq=1e-6 * k, less_noise_var=1e-12 * k)


def test_plus_sums_the_noise_and_its_uncertainty() -> None:
    both = generation(1.0).plus(generation(2.0))
    assert both.carried_noise_sq == pytest.approx(3e-6)
    assert both.less_noise_var == pytest.approx(3e-12)
    assert both.carried_less_noise_dps == pytest.approx(math.sqrt((12e-6 - 3e-6) / 8))


def test_all_noise_is_reported_as_zero_with_an_upper_bound() -> None:
    g = Generation(stops=4, error_sq=0.0, heading_sq=0.0, drives=1, carried_sq=1e-6, carried_noise_sq=2e-6,
                   less_noise_var=4e-12)
    assert g.carried_less_noise_dps == 0.0
    assert g.carried_less_noise_sd_dps == pytest.approx(math.sqrt((1e-6 - 2e-6 + 2e-6) / 4))


def test_replay_csv_has_the_noise_columns_beside_the_old_ones() -> None:
    v = VehicleResult("veh-00000", "D26-00000", 10, generation(1.0), generation(2.0))
    header, line = vehicles_csv([v]).splitlines()
    cols = dict(zip(header.split(","), line.split(","), strict=True))
    assert header.startswith("vehicle_id,sensor_id,drives,rows,standstills,carried_before_dps,"
                             "carried_after_dps,zero_rate_before_dps,zero_rate_after_dps,"
                             "heading_before_deg,heading_after_deg,")
    assert float(cols["carried_noise_before_dps"]) == pytest.approx(math.sqrt(1e-6 / 4), rel=1e-5)
    assert float(cols["carried_less_noise_after_dps"]) == pytest.approx(math.sqrt(6e-6 / 4), rel=1e-5)
    assert float(cols["carried_less_noise_after_sd_dps"]) > 0
