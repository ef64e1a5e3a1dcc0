"""The noise of a standstill's mean, estimated from the standstill itself (``fleet replay``).

Why: a standstill's carried figure is the mean of its rows, so its square is on average the
error squared plus that mean's variance (the white noise and the engine's idle vibration, which
no set removes). Summed over standstills, m² less that variance is an unbiased estimate of the
error itself, and it needs no truth: a fleet engineer can tell what a set changed from the
noise's floor.

Why one-second means about a line, not the sample variance over n: the idle vibration is a tone
of 20-30 Hz, large per sample (0.1 deg/s) and nearly gone in a mean; the rows are not
independent, and the naive variance over n overstates the mean's noise (about five times in
variance on the simulated drives). The means of one-second pieces (the tracker's window) are
nearly independent, and their spread over their count is the mean's variance, whatever the
noise's colour within a second. About a line: a stop with a wrong slope warms a little while it
lasts, and that trend is error, not noise. What it cannot see: noise correlated over more than a
second (a wander slower than the pieces, not straight) is counted as error, not noise.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The pieces a standstill is cut into to estimate its mean's noise (s): the tracker's window.
PIECE_S = 1.0
#: Fewer whole pieces than this and a line leaves no spread to estimate from.
MIN_PIECES = 3


@dataclass(frozen=True)
class MeanNoise:
    """Summed over standstills: their means' estimated variance, and the variance that noise
    leaves in the sum of m² less it (for its uncertainty), both (deg/s)² or its square."""

    variance: float
    less_noise_var: float

    def plus(self, other: MeanNoise) -> MeanNoise:
        return MeanNoise(self.variance + other.variance, self.less_noise_var + other.less_noise_var)


class StopSeconds:
    """One standstill's rows summed a piece of :data:`PIECE_S` at a time, fed block by block
    (the pieces are cut by time since the standstill began, so any cut into blocks gives the same
    pieces)."""

    def __init__(self, start_s: float = 0.0) -> None:
        self.start_s = start_s
        self.rows = 0
        self.sums: list[np.ndarray] = []  # whole pieces' sums and row counts, and their index
        self.counts: list[np.ndarray] = []
        self.keys: list[np.ndarray] = []
        self.open = (-1, 0.0, 0)  # the piece still filling: index, sum, rows

    def add(self, time_s: np.ndarray, values: np.ndarray) -> None:
        """The next rows of the standstill (times rising)."""
        if not len(values):
            return
        self.rows += len(values)
        idx = np.floor((time_s - self.start_s) / PIECE_S).astype(np.int64)
        first = int(idx[0])
        sums = np.bincount(idx - first, weights=values)
        counts = np.bincount(idx - first)
        keys = np.flatnonzero(counts)
        sums, counts, keys = sums[keys], counts[keys], keys + first
        key, total, n = self.open
        if keys[0] == key:
            sums[0] += total
            counts[0] += n
        elif n:
            self._keep(np.array([total]), np.array([n]), np.array([key]))
        self._keep(sums[:-1], counts[:-1], keys[:-1])
        self.open = (int(keys[-1]), float(sums[-1]), int(counts[-1]))

    def _keep(self, sums: np.ndarray, counts: np.ndarray, keys: np.ndarray) -> None:
        self.sums.append(sums)
        self.counts.append(counts)
        self.keys.append(keys)

    def noise(self, mean: float) -> MeanNoise:
        """The variance of the standstill's mean of all its rows, from its whole pieces' means
        about a line; and the variance its noise leaves in ``mean² -`` that (m ~ N(b, v): m² has
        4b²v + 2v², the estimate 2v²/(k - 2) more). Too few pieces: nothing estimated (0)."""
        if not self.sums:
            return MeanNoise(0.0, 0.0)
        counts, keys = np.concatenate(self.counts), np.concatenate(self.keys).astype(float)
        if len(keys) < MIN_PIECES:
            return MeanNoise(0.0, 0.0)
        means = np.concatenate(self.sums) / counts
        resid = means - np.polyval(np.polyfit(keys, means, 1), keys)
        dof = len(keys) - 2
        v = float(resid @ resid) / dof * float(counts.mean()) / self.rows
        square = max(mean * mean - v, 0.0)
        return MeanNoise(v, 4 * square * v + 2 * v * v + 2 * v * v / dof)
