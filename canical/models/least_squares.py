"""Linear least squares through the normal equations where they are well conditioned.

The closed loop solves the same small problems (a few thousand rows, a score of columns) tens of
thousands of times: every time constant tried in every cross-validation fold. ``numpy.linalg.lstsq``
factors each one by SVD; the normal equations of the column-scaled design cost a fifth of that,
and their Gram matrix can be kept and bordered when only the last columns change (a time
constant's feature), so that trying a column costs its own products alone.

The normal equations square the design's condition number. They are used only while the scaled
design's condition number stays under :data:`MAX_CONDITION`, where a prediction's error from
rounding is about machine epsilon × that number × the data's size (under 1e-9 deg/s on a
300 deg/s table); otherwise, and where a column is zero, the SVD solves it, as before.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

#: The largest condition number of the column-scaled design solved through the normal equations.
MAX_CONDITION = 1e5


@dataclass(frozen=True)
class NormalEquations:
    """A least-squares problem ``x @ c ≈ y``, its columns and their Gram matrix and right-hand side.

    ``extra``: columns bordered onto ``x`` by :meth:`bordered`, kept apart so that the SVD
    fallback is the only place the full design is ever stacked.
    """

    x: np.ndarray
    y: np.ndarray
    gram: np.ndarray
    rhs: np.ndarray
    extra: np.ndarray | None = None

    @classmethod
    def of(cls, x: np.ndarray, y: np.ndarray) -> NormalEquations:
        """The normal equations of ``x @ c ≈ y``."""
        return cls(x, y, x.T @ x, x.T @ y)

    def bordered(self, extra: np.ndarray) -> NormalEquations:
        """The problem with ``extra``'s columns after ``x``'s: only their own products are computed."""
        if self.extra is not None:
            raise ValueError("bordered twice: border the first problem with every extra column")
        n = self.gram.shape[0]
        gram = np.empty((n + extra.shape[1],) * 2)
        gram[:n, :n] = self.gram
        gram[:n, n:] = self.x.T @ extra
        gram[n:, :n] = gram[:n, n:].T
        gram[n:, n:] = extra.T @ extra
        return NormalEquations(self.x, self.y, gram, np.concatenate([self.rhs, extra.T @ self.y]), extra)

    def solve(self) -> np.ndarray:
        """The least-squares coefficients: by the scaled normal equations when they are well
        conditioned, else by SVD (the minimum-norm solution where columns are dependent)."""
        norms = np.sqrt(np.diag(self.gram))
        if np.all(norms > 0):
            scaled = self.gram / np.outer(norms, norms)
            eigen = np.linalg.eigvalsh(scaled)
            if eigen[0] > eigen[-1] / MAX_CONDITION**2:
                solution: np.ndarray = np.linalg.solve(scaled, self.rhs / norms) / norms
                return solution
        x = self.x if self.extra is None else np.hstack([self.x, self.extra])
        fallback: np.ndarray = np.linalg.lstsq(x, self.y, rcond=None)[0]
        return fallback
