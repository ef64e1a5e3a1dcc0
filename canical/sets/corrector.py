"""Apply a coefficient set to raw samples: the run-time side of a calibration.

Built once from a validated set (everything that can be computed at load is
computed here), then called per block of samples (``correct``) or per frame
(``correct_one``). It never sees a reference rate: in the field there is none.

Effect terms correct the raw output before the rate model (see
:mod:`canical.sets.terms`). A gated term reads ΔV as well, without state. A
direction or slope term, and a channel's lag, derivative or direction term, has
state, so one Corrector
serves one stream of samples in time order; ``correct`` on a block starts from
a fresh state, exactly as ``correct_one`` does on a new Corrector, so the two
agree sample for sample. ``correct_next`` carries that state from one block to the next, so a
long stream corrected block by block gives, bit for bit, what one ``correct`` of it gives.
"""

from __future__ import annotations

from collections.abc import Mapping
from typing import Any

import numpy as np

from canical.errors import CanicalError
from canical.models.piecewise import PiecewisePoly
from canical.sets.coefficient_file import set_crc
from canical.sets.coefficients import CoefficientSet
from canical.sets.term_kinds import TermMaths, Tracker
from canical.sets.terms import Term, feature_values, raw_shift


class Corrector:
    """ΔV = raw − V0 → ω through the set's rate model, plus its effect terms."""

    def __init__(self, cset: CoefficientSet) -> None:
        self.cset = cset
        self.v0 = float(cset.v0)
        self.model = cset.rate_model()
        self.set_id = set_crc(cset)
        self.terms: tuple[Term, ...] = cset.terms
        self.kinds: tuple[TermMaths, ...] = tuple(t.spec for t in self.terms)
        names = [n for t in self.terms for n in t.input_names]
        self.required_inputs: tuple[str, ...] = tuple(dict.fromkeys(names))
        self.reset()

    def reset(self) -> None:
        """Forget the direction, slope, lag and derivative state (a new stream of samples begins)."""
        self._trackers = [t.spec.tracker(t) for t in self.terms]
        # Per term, what correct_one reads, looked up once: a frame pays only the calls.
        self._steps = tuple((t.spec.one, t, tracker, t.coefficient, t.form == "scale")
                            for t, tracker in zip(self.terms, self._trackers, strict=True))

    def correct(
        self, raw: np.ndarray, inputs: Mapping[str, np.ndarray] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """Calibrated rate (deg/s) and out-of-span flags for a block of samples in time order."""
        raw = np.asarray(raw, dtype=float)
        inputs = inputs or {}
        missing = [n for n in self.required_inputs if n not in inputs]
        if missing:
            raise CanicalError(f"the coefficient set needs input(s) {', '.join(missing)}")
        dv = raw - self.v0
        if self.terms:
            features = np.column_stack([feature_values(t, inputs, raw, dv) for t in self.terms])
            dv = dv - raw_shift(self.terms, features, dv)
        return self.model.evaluate(dv)

    def correct_next(
        self, raw: np.ndarray, inputs: Mapping[str, np.ndarray] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """:meth:`correct` for the next block of the stream, its state carried from the previous
        block (the stream starts at construction or :meth:`reset`).

        Bit for bit what one :meth:`correct` of the blocks joined gives, for a rate model that
        evaluates each sample on its own (``elementwise_model``).
        """
        raw = np.asarray(raw, dtype=float)
        inputs = inputs or {}
        missing = [n for n in self.required_inputs if n not in inputs]
        if missing:
            raise CanicalError(f"the coefficient set needs input(s) {', '.join(missing)}")
        dv = raw - self.v0
        if self.terms:
            features = np.column_stack([
                spec.values_from(t, tracker, inputs, raw, dv)
                for t, spec, tracker in zip(self.terms, self.kinds, self._trackers, strict=True)
            ])
            dv = dv - raw_shift(self.terms, features, dv)
        return self.model.evaluate(dv)

    @property
    def trackers(self) -> tuple[Tracker | None, ...]:
        """Each term's state for the stream this corrector follows (None: a stateless term); the
        compiled corrector carries on from, and updates, these same objects."""
        return tuple(self._trackers)

    @property
    def elementwise_model(self) -> bool:
        """Whether the rate model evaluates each sample on its own (a piecewise polynomial); the
        forward polynomial's Newton iterates until the whole block has converged, so its result
        for a sample depends on the block it is in."""
        return isinstance(self.model, PiecewisePoly)

    def correct_one(self, raw: float, inputs: Mapping[str, float] | None = None) -> tuple[float, bool]:
        """Calibrated rate and out-of-span flag for the next sample of the stream."""
        raw = float(raw)
        dv = raw - self.v0
        shift = 0.0
        values: Any = inputs
        for one, term, tracker, coefficient, scales in self._steps:
            x = one(term, tracker, raw, dv, values)
            shift += coefficient * (x * dv if scales else x)
        return self.model.evaluate_one(dv - shift)
