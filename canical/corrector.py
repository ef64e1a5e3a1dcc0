"""Apply a coefficient set to raw samples: the run-time side of a calibration.

Built once from a validated set (everything that can be computed at load is
computed here), then called per block of samples (``correct``) or per frame
(``correct_one``). It never sees a reference rate: in the field there is none.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from canical.coefficient_file import set_crc
from canical.coefficients import CoefficientSet


class Corrector:
    """ΔV = raw − V0 → ω through the set's rate model."""

    def __init__(self, cset: CoefficientSet) -> None:
        self.cset = cset
        self.v0 = float(cset.v0)
        self.model = cset.rate_model()
        self.set_id = set_crc(cset)

    @property
    def required_inputs(self) -> tuple[str, ...]:
        """Auxiliary inputs (by name) the set's terms need at run time."""
        return ()

    def correct(
        self, raw: np.ndarray, inputs: Mapping[str, np.ndarray] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Calibrated rate (deg/s) and out-of-span flags for a block of samples in time order."""
        return self.model.evaluate(np.asarray(raw, dtype=float) - self.v0)

    def correct_one(self, raw: float, inputs: Mapping[str, float] | None = None) -> tuple[float, bool]:
        """Calibrated rate and out-of-span flag for one sample."""
        return self.model.evaluate_one(float(raw) - self.v0)
