"""Apply an IMU set to raw samples of the three axes: each axis's corrector, then the coupling.

Each channel goes through its own axis's :class:`~canical.sets.corrector.Corrector` (rate model
and effect terms, unchanged), and the three corrected rates through the coupling matrix:
``corrected = M @ [x, y, z]``. A sample's out-of-span flag is its own channel's: the coupling
mixes rates, but only a raw value outside its axis's calibrated span is extrapolated.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import TypeVar

import numpy as np

from canical.sets.corrector import Corrector
from canical.sets.imu_set import ImuSet, Matrix, imu_set_crc

Rate = TypeVar("Rate", float, np.ndarray)


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
        coupled = couple(self.imu.coupling, rates[:, 0], rates[:, 1], rates[:, 2])
        return np.column_stack(coupled), flags


def couple(m: Matrix, x: Rate, y: Rate, z: Rate) -> tuple[Rate, Rate, Rate]:
    """``m @ [x, y, z]`` on floats or arrays, each row summed left to right.

    Why written out: the daemon's generated code (:func:`coupling_lines`) and this evaluate the
    same products in the same order, so a frame's coupled rates equal ``apply``'s bit for bit
    (a matrix product may sum in another order, or fused)."""
    (a, b, c), (d, e, f), (g, h, i) = m
    return a * x + b * y + c * z, d * x + e * y + f * z, g * x + h * y + i * z


def coupling_lines(m: Matrix, names: tuple[str, str, str]) -> list[str]:
    """Statements replacing the three corrected rates (variables ``names``) by ``m @ rates``,
    as :func:`couple` computes it (the constants written in)."""
    x, y, z = names
    rows = [" + ".join(f"{coef!r} * {v}" for coef, v in zip(row, names, strict=True)) for row in m]
    return [f"    {x}, {y}, {z} = {rows[0]}, {rows[1]}, {rows[2]}"]
