"""Apply an IMU set to raw samples of the three axes: each axis's corrector, then the coupling.

Each channel goes through its own axis's :class:`~canical.sets.corrector.Corrector` (rate model
and effect terms, unchanged), and the three corrected rates through the coupling matrix:
``corrected = M @ [x, y, z]``. A sample's out-of-span flag is its own channel's: the coupling
mixes rates, but only a raw value outside its axis's calibrated span is extrapolated.
"""

from __future__ import annotations

from collections.abc import Mapping

import numpy as np

from canical.sets.corrector import Corrector
from canical.sets.imu_set import ImuSet, imu_set_crc


class ImuCorrector:
    """Raw (n, 3) → rates (n, 3) in deg/s, with per-axis out-of-span flags."""

    def __init__(self, imu: ImuSet) -> None:
        self.imu = imu
        self.axes = tuple(Corrector(cset) for cset in imu.axes)
        self.matrix = imu.matrix()
        self.set_id = imu_set_crc(imu)
        names = [n for c in self.axes for n in c.required_inputs]
        self.required_inputs: tuple[str, ...] = tuple(dict.fromkeys(names))

    def per_axis(self, raw: np.ndarray, inputs: Mapping[str, np.ndarray] | None = None
                 ) -> tuple[np.ndarray, np.ndarray]:
        """Each channel through its own axis's set alone (no coupling), and the flags."""
        raw = np.asarray(raw, dtype=float)
        out = [c.correct(raw[:, i], inputs) for i, c in enumerate(self.axes)]
        return np.column_stack([r for r, _ in out]), np.column_stack([o for _, o in out])

    def correct(self, raw: np.ndarray, inputs: Mapping[str, np.ndarray] | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
        """Calibrated rates (n, 3) and out-of-span flags (n, 3) for a block of samples in time order."""
        rates, flags = self.per_axis(raw, inputs)
        return rates @ self.matrix.T, flags
