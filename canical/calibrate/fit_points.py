"""The points a model is fitted to: one per plateau, averaged over its settled samples.

Averaging first makes a million-sample session cost what a forty-plateau one
does, and it is what the paper fits (one point per table rate). Each point
keeps its sample count (the weight) and the standard error of its mean, so
segment-point selection can tell a real residual extremum from noise; and the standard
error of its table rate, which a *measured* reference (encoder jitter) adds to that noise.
"""

from __future__ import annotations

from dataclasses import dataclass
from functools import cached_property

import numpy as np

from canical.calibrate.plateaus import Plateaus, plateau_means, plateau_stds

RATE_GROUP_TOL_DPS = 0.05


@dataclass(frozen=True)
class FitPoints:
    """Plateau means: the table rate ω and the sensor's ΔV = raw − V0."""

    rate: np.ndarray  # deg/s, per plateau
    dv: np.ndarray  # raw units, per plateau
    weight: np.ndarray  # samples per plateau
    dv_sem: np.ndarray  # standard error of the mean of ΔV, raw units
    #: Standard error of each point's table rate, deg/s: a measured reference's jitter averaged
    #: over the plateau (None: an exact, commanded reference).
    rate_sem: np.ndarray | None = None

    def __len__(self) -> int:
        return int(self.rate.shape[0])

    def take(self, index: np.ndarray) -> FitPoints:
        rate_sem = None if self.rate_sem is None else self.rate_sem[index]
        return FitPoints(self.rate[index], self.dv[index], self.weight[index], self.dv_sem[index], rate_sem)

    def rate_uncertainty(self) -> np.ndarray:
        """Per point: the standard error of its table rate (0 for an exact reference)."""
        return np.zeros(len(self)) if self.rate_sem is None else self.rate_sem

    def rate_groups(self, tol: float = RATE_GROUP_TOL_DPS) -> np.ndarray:
        """Group index per point: plateaus at the same table rate (repeated sweeps) share one.

        The tolerance is wider than a measured reference's scatter of plateau means (its
        jitter over a plateau's updates), far narrower than any useful rate step.
        """
        order = np.argsort(self.rate, kind="stable")
        sorted_rate = self.rate[order]
        new = np.concatenate(([True], np.diff(sorted_rate) > tol))
        groups = np.empty(len(self), dtype=np.int64)
        groups[order] = np.cumsum(new) - 1
        return groups

    def by_rate(self) -> FitPoints:
        """One point per distinct rate, sorted by rate: repeated sweeps merged by weight (merged
        once: a model selection asks for it in every fit of every size)."""
        return self._merged

    @cached_property
    def _merged(self) -> FitPoints:
        groups = self.rate_groups()
        n = int(groups.max()) + 1 if len(self) else 0
        w = np.bincount(groups, self.weight, n)
        rate = np.bincount(groups, self.rate * self.weight, n) / w
        dv = np.bincount(groups, self.dv * self.weight, n) / w
        # Combine standard errors as independent means weighted by sample count.
        var = np.bincount(groups, (self.dv_sem * self.weight) ** 2, n) / w**2
        rate_sem = None
        if self.rate_sem is not None:
            rate_sem = np.sqrt(np.bincount(groups, (self.rate_sem * self.weight) ** 2, n) / w**2)
        return FitPoints(rate, dv, w, np.sqrt(var), rate_sem)


def fit_points(raw: np.ndarray, v0: float, plateaus: Plateaus, samples_per_row: int = 1) -> FitPoints:
    """Reduce a session to plateau means of ΔV at each plateau's table rate.

    ``samples_per_row``: a session read as means of that many samples. The standard error
    comes from the rows (a mean's spread is already a sample's over √k); the weight counts
    samples, so that ``dv_sem·√weight`` stays one sample's spread.
    """
    dv = plateau_means(raw, plateaus) - v0
    n = (plateaus.stop - plateaus.start).astype(float)
    sem = plateau_stds(raw, plateaus) / np.sqrt(n)
    ref_sem = plateaus.rate_uncertainty()
    return FitPoints(plateaus.rate_dps.copy(), dv, n * samples_per_row, sem,
                     ref_sem.copy() if np.any(ref_sem > 0) else None)
