"""A long session's channels are kept as means of a few samples for the loop's transforms.

Why: every τ, knee and candidate the loop tries is a pass over the kept samples; at 10 million
rows with two channels those passes were the whole run (issue 32, "channels at scale"). The means
never straddle a block's edge, and weigh by their samples, so a block's mean of a channel is
exact and its lag, derivative and gate are within a small share of the per-sample ones.
"""

from __future__ import annotations

import numpy as np
import pytest

from canical.closed_loop import blocks

FS_HZ = 1000.0


@pytest.fixture
def record() -> dict[str, np.ndarray]:
    """200,000 samples at 1 kHz: a channel cycling with noise, ΔV through a knee, 2 s blocks with gaps."""
    rng = np.random.default_rng(3)
    n = 200_000
    t = np.arange(n) / FS_HZ
    starts = np.arange(0, n - 2000, 2137)
    return {"t": t, "temp": 25.0 + 10.0 * np.sin(2 * np.pi * t / 60.0) + 0.02 * rng.standard_normal(n),
            "dv": 400.0 * np.repeat(np.linspace(-60, 60, n // 2000), 2000) + 30.0 * rng.standard_normal(n),
            "starts": starts, "stops": starts + 2000}


def test_above_the_bound_the_channels_are_means_within_blocks(record, monkeypatch) -> None:
    monkeypatch.setattr(blocks, "FEATURE_SAMPLES", 20_000)
    aux = {"temp_c": record["temp"]}
    full = blocks.ChannelSamples(record["t"], aux, record["starts"], record["stops"], dv=record["dv"])
    kept = blocks.channel_samples(record["t"], aux, record["starts"], record["stops"], record["dv"])
    assert kept.time_s.size <= 20_000 + 2 * record["starts"].size < record["t"].size
    np.testing.assert_allclose(kept.means(kept.values["temp_c"]), full.means(record["temp"]), rtol=1e-12)
    np.testing.assert_allclose(kept.means(kept.time_s), full.means(record["t"]), rtol=1e-12)
    for tau in (0.5, 5.0, 60.0):  # a lag moves little within 10 ms
        np.testing.assert_allclose(kept.lag_means("temp_c", tau), full.lag_means("temp_c", tau), atol=0.01)
    knee = 400.0 * 20.0  # the gate of a mean differs from the mean of gates only near the knee
    gated, exact = kept.gated_means("temp_c", 25.0, knee), full.gated_means("temp_c", 25.0, knee)
    assert np.max(np.abs(gated - exact)) < 0.01 * np.ptp(exact)


def test_within_the_bound_the_samples_are_kept_as_they_are(record) -> None:
    kept = blocks.channel_samples(record["t"], {"temp_c": record["temp"]}, record["starts"], record["stops"],
                                  record["dv"])
    assert kept.weights is None and kept.time_s is record["t"]


def per_sample_gated_means(samples: blocks.ChannelSamples, channel: str, reference: float,
                           knee: float) -> np.ndarray:
    """The definition: each block's mean of (v − r)·g(ΔV) taken sample by sample."""
    assert samples.dv is not None
    gated = (samples.values[channel] - reference) * blocks.rate_gate(samples.dv, knee)
    return samples.means(gated)


@pytest.mark.parametrize("bound", [None, 20_000])
def test_a_gated_level_is_its_per_sample_mean_at_every_knee(record, monkeypatch, bound) -> None:
    """Blocks wholly beyond the knee, wholly below it and straddling it (noise about a rate near
    the knee), on samples as they are and on kept means: what a knee search is given is exact."""
    if bound is not None:
        monkeypatch.setattr(blocks, "FEATURE_SAMPLES", bound)
    kept = blocks.channel_samples(record["t"], {"temp_c": record["temp"]}, record["starts"],
                                  record["stops"], record["dv"])
    for knee in (0.0, 10.0, 400.0 * 20.0 + 5.0, 400.0 * 59.0, 400.0 * 80.0):
        np.testing.assert_allclose(kept.gated_means("temp_c", 25.0, knee),
                                   per_sample_gated_means(kept, "temp_c", 25.0, knee), rtol=1e-9, atol=1e-9)
