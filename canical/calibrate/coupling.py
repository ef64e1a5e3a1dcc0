"""The coupling between a triad's axes: a 3×3 matrix from plateau means, with standard errors.

The estimation, and why:

1. **Per-axis models first.** Each axis's rate model (the segmented inverse and the closed loop,
   unchanged) is fitted on its own session's own raw channel. On that session the other two axes
   are at rest, so the channel sees only its own axis's rate: coupling cannot bias its model. The
   model is fitted to the table's rate, which fixes each axis's scale (the matrix's diagonal
   comes out ≈ 1).
2. **The coupling from all sessions' plateaus.** Through the per-axis models every plateau of
   every session gives the per-axis rates ``u`` (3 values) beside the true rate vector ``ω``
   (the table's rate on the turning axis, zero on the others). On the x session the y and z
   outputs see only what leaks from the x rate, so each session measures one column. The model
   is ``u = C ω + e``: ``C`` is what each axis senses of each true axis. It is fitted by least
   squares with the *table* rates as regressors, because they are exact and the noise is in
   ``u``, so the estimate is unbiased (regressing ω on u would attenuate it); each row of ``C``
   is one channel's least squares. The matrix written is ``M = C⁻¹`` (corrected = M @ u).
3. **Standard errors** from the residual covariance Σ (3×3, across channels) and the design:
   ``cov(C_ik, C_jl) = Σ_ij [(ΩᵀΩ)⁻¹]_kl``, carried to ``M`` by ``dM = −M dC M``, which gives
   ``var(M_ab) = (m_aᵀ Σ m_a)(n_bᵀ (ΩᵀΩ)⁻¹ n_b)`` with ``m_a`` row a and ``n_b`` column b of M.

4. **Then a joint refit** (:mod:`canical.calibration.imu_pipeline`): step 1 is consistent (a channel's own
   session carries no coupling), but the other sessions read each axis's model only at a few
   deg/s, where its own session has few plateaus; refitting each model with those plateaus
   (targets from C) and C through the new models lowers the error there.

The standard errors count the plateaus' noise and the per-axis models' own error (which does not
average out over plateaus: :func:`term_covariance`); on simulated triads every term comes out
within 3 of them (tests/test_imu_pipeline.py, tests/benchmarks/bench_triad.py).
Pure numpy; no files.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from canical.errors import CanicalError


@dataclass(frozen=True)
class CouplingFit:
    """The coupling as estimated: ``matrix`` M (corrected = M @ per-axis rates) and its errors."""

    matrix: np.ndarray  # (3, 3)
    standard_errors: np.ndarray  # (3, 3), one per term of M
    sensed: np.ndarray  # C = M⁻¹: what each axis senses of each true axis
    residual_dps: np.ndarray  # (N, 3): u − C ω at the fitted plateaus
    points: int


def fit_coupling(true_dps: np.ndarray, per_axis_dps: np.ndarray,
                 model_error_dps: np.ndarray | None = None) -> CouplingFit:
    """Least squares of the per-axis rates on the true rate vectors (see the module docstring).

    ``model_error_dps`` (per axis: its rate model's held-out rms) adds the models' own error to
    the standard errors: see :func:`term_covariance`.
    """
    omega = np.asarray(true_dps, dtype=float)
    u = np.asarray(per_axis_dps, dtype=float)
    n = omega.shape[0]
    if n <= 3 or np.linalg.matrix_rank(omega) < 3:
        raise CanicalError("the plateaus do not turn three independent axes: the coupling cannot be fitted")
    design = np.linalg.inv(omega.T @ omega)
    sensed = (design @ omega.T @ u).T
    residual = u - omega @ sensed.T
    sigma = residual.T @ residual / (n - 3)
    matrix = np.linalg.inv(sensed)
    cov = term_covariance(sigma, design, omega, model_error_dps)
    jacobian = -np.einsum("ai,kb->abik", matrix, matrix).reshape(9, 9)  # dM = −M dC M
    errors = np.sqrt(np.diag(jacobian @ cov @ jacobian.T)).reshape(3, 3)
    return CouplingFit(matrix, errors, sensed, residual, n)


def term_covariance(sigma: np.ndarray, design: np.ndarray, omega: np.ndarray,
                    model_error_dps: np.ndarray | None) -> np.ndarray:
    """Covariance of C's nine terms (row-major): the plateaus' noise, and the models' own error.

    Noise: ``cov(C_ik, C_jl) = Σ_ij [(ΩᵀΩ)⁻¹]_kl``. A per-axis model's error is not noise: it is
    the same at the same rate on every pass, so it does not average out over plateaus. Axis ``i``'s
    model, wrong by about its held-out rms ``h_i`` where another session reads it, moves
    ``C_ik`` by about ``h_i / ω_k`` with ``ω_k`` the rms table rate of the session turning axis
    ``k``: that is added to each term, independently (a bound of the right size; the models'
    errors at the few deg/s the other sessions read them are not known better than their held-out
    rms). Without it, on simulated triads the terms came out up to 12 standard errors off.
    """
    cov = np.kron(sigma, design)
    if model_error_dps is None:
        return cov
    turning = np.array([np.sqrt(np.mean(np.square(omega[omega[:, k] != 0, k]))) for k in range(3)])
    h = np.asarray(model_error_dps, dtype=float)
    return cov + np.diag(np.square(h[:, None] / turning[None, :]).ravel())


def held_out_corrected(true_dps: np.ndarray, per_axis_dps: np.ndarray) -> np.ndarray:
    """Each plateau corrected with the coupling fitted without it (leave one plateau out), (N, 3)."""
    omega = np.asarray(true_dps, dtype=float)
    u = np.asarray(per_axis_dps, dtype=float)
    out = np.empty_like(u)
    for p in range(omega.shape[0]):
        keep = np.arange(omega.shape[0]) != p
        out[p] = fit_coupling(omega[keep], u[keep]).matrix @ u[p]
    return out


def angle_mrad(term: float) -> float:
    """A small coupling term as the angle it tilts an axis by, mrad."""
    return 1000.0 * float(np.arctan(term))
