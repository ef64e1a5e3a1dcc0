"""The paper's three calibration models, each a fitter returning a run-time model.

* :mod:`~canical.models.forward_poly` — ΔV(ω) as one polynomial (eq. 5), inverted numerically;
* :mod:`~canical.models.segmented_linear` — the common model (eq. 6), linear per rate segment;
* :mod:`~canical.models.segmented_inverse` — the improved model (eqs. 10, 11), ω(ΔV) per segment;
* :mod:`~canical.models.kinds` — the registry naming them (one object per kind, the names in files).

A run-time model maps ΔV to ω, vectorised (:meth:`RateModel.evaluate`) and one
sample at a time (:meth:`RateModel.evaluate_one`, the daemon's per-frame path).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Protocol

from canical.models import kinds as _kinds

if TYPE_CHECKING:  # kept out of start-up: `canical calibrate --help` lists MODEL_KINDS
    import numpy as np

# The package's public face: the submodules (and names) other rings and the tests import;
# tests/test_rings.py keeps this list equal to those imports.
__all__ = [
    "MODEL_KINDS",
    "RateModel",
    "forward_poly",
    "kinds",
    "least_squares",
    "piecewise",
    "robust_stats",
    "segmented_inverse",
    "segmented_linear",
]

MODEL_KINDS = _kinds.MODEL_KINDS


class RateModel(Protocol):
    """ΔV → ω, with a flag for values outside the calibrated span."""

    @property
    def span(self) -> tuple[float, float]:
        """The calibrated ΔV span (read-only: a field on some models, computed on others)."""
        ...

    def evaluate(self, dv: np.ndarray) -> tuple[np.ndarray, np.ndarray]: ...

    def evaluate_one(self, dv: float) -> tuple[float, bool]: ...
