"""The coupling least squares: unbiased with exact table rates, standard errors that mean what they say."""

import numpy as np
import pytest

from canical.calibrate.coupling import angle_mrad, fit_coupling, held_out_corrected
from canical.errors import CanicalError


def plateaus(rng, sensed, noise=0.003):
    """Three single-axis sessions' plateaus: true rate vectors and noisy per-axis rates."""
    rates = np.concatenate([np.arange(-150, 151, 10.0)] * 2)
    true = np.vstack([np.outer(rates, np.eye(3)[i]) for i in range(3)])
    return true, true @ sensed.T + noise * rng.standard_normal(true.shape)


def test_standard_errors_cover_the_truth():
    """Over many draws, the error of each term divided by its standard error is ~N(0, 1)."""
    z = []
    for seed in range(200):
        rng = np.random.default_rng(seed)
        sensed = np.eye(3) + rng.uniform(-0.02, 0.02, (3, 3)) * (1 - np.eye(3))
        fit = fit_coupling(*plateaus(rng, sensed))
        z.append((fit.matrix - np.linalg.inv(sensed)) / fit.standard_errors)
    z_all = np.array(z)
    assert 0.85 < z_all.std() < 1.15
    assert np.mean(np.abs(z_all) < 3) > 0.99


def test_held_out_correction_and_angles():
    rng = np.random.default_rng(1)
    sensed = np.eye(3) + 0.01 * (1 - np.eye(3))
    true, u = plateaus(rng, sensed)
    err = held_out_corrected(true, u) - true
    assert np.sqrt(np.mean(err**2)) < 0.01
    assert angle_mrad(0.01) == pytest.approx(9.9997, abs=1e-3)


def test_plateaus_of_one_axis_cannot_give_a_coupling():
    true = np.outer(np.arange(-50, 51, 10.0), [1.0, 0, 0])
    with pytest.raises(CanicalError, match="three independent axes"):
        fit_coupling(true, true)
