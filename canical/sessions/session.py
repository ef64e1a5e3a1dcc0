"""A calibration session as plain data: what the rate table and the sensor recorded.

One row per sample. ``ref_dps`` is the table's rate (absent when the data comes
from the field, where there is no reference); ``raw`` is the sensor output for
the calibrated axis before any correction; ``aux`` holds every other numeric
channel by its column name, whose meaning the calibrator is not told.
``settled`` is the table's own settled flag when the recording has one: it is
not an auxiliary channel (it says how the table moves, not what the sensor feels).
"""

from __future__ import annotations

from dataclasses import dataclass, field

import numpy as np

from canical.errors import CanicalError


@dataclass(frozen=True)
class Rail:
    """The limits of the raw signal as its definition gives them: values there are clipped.

    From the DBC (bit width, scale, offset, declared range), a CSV's ``# rail: LO,HI`` line or
    ``--rail``; never from the values recorded. ``resolution`` is the signal's step (a value
    within half a step of a limit is at it); ``source`` says where the limits come from.
    """

    low: float
    high: float
    source: str
    resolution: float = 0.0


def parse_rail(text: str, source: str) -> Rail:
    """``LO,HI`` as a rail; one line naming ``source`` when it is not two finite numbers, LO < HI."""
    parts = text.split(",")
    try:
        low, high = (float(p) for p in parts) if len(parts) == 2 else (float("nan"),) * 2
    except ValueError:
        low = high = float("nan")
    if not (np.isfinite(low) and np.isfinite(high) and low < high):
        raise CanicalError(f"{source}: rail {text.strip()!r}: expected LO,HI (two numbers, LO below HI)")
    return Rail(low, high, source)


#: The metadata key of the raw values' unit (a CSV's ``# raw_units:`` line, a log's DBC signal unit).
RAW_UNITS = "raw_units"


@dataclass(frozen=True)
class RowMeans:
    """How a session too long to hold was read: each row the mean of ``k`` consecutive samples.

    Why: a session of tens of millions of samples does not fit in memory, yet plateaus, blocks
    and fit points are means anyway. What a mean hides and calibration needs is kept beside it:
    ``raw_low``/``raw_high`` are the lowest and highest raw sample behind each row, so a row
    touches a rail when any of its samples did.
    """

    rows_read: int  # samples in the file
    k: int  # samples per row (the last row may have fewer)
    raw_low: np.ndarray
    raw_high: np.ndarray

    def line(self) -> str:
        """The one line calibrate prints and reports."""
        return f"{self.rows_read:,} rows read as {self.raw_low.size:,} means of {self.k}"

    def take(self, index: np.ndarray) -> RowMeans:
        return RowMeans(self.rows_read, self.k, self.raw_low[index], self.raw_high[index])


@dataclass(frozen=True)
class Session:
    """Samples of one axis, in time order."""

    time_s: np.ndarray
    raw: np.ndarray
    ref_dps: np.ndarray | None = None
    aux: dict[str, np.ndarray] = field(default_factory=dict)
    meta: dict[str, str] = field(default_factory=dict)
    settled: np.ndarray | None = None
    rail: Rail | None = None  # the raw signal's limits, when its definition or the user gives them
    means: RowMeans | None = None  # a long session read as means of consecutive samples

    @property
    def samples_per_row(self) -> int:
        """How many recorded samples each row stands for (1: the samples themselves)."""
        return 1 if self.means is None else self.means.k

    @property
    def samples_read(self) -> int:
        """How many samples the recording holds (rows, or the rows the means were made of)."""
        return len(self) if self.means is None else self.means.rows_read

    def __len__(self) -> int:
        return int(self.raw.shape[0])

    @property
    def sensor_id(self) -> str | None:
        """The sensor's identifier when the recording declares one."""
        return self.meta.get("sensor")

    @property
    def axis(self) -> str | None:
        """The recorded axis when the recording declares it."""
        return self.meta.get("axis")

    def reference(self, purpose: str = "calibrate") -> np.ndarray:
        """The table rate, for the steps that need one; a field recording has none to give."""
        if self.ref_dps is None:
            raise CanicalError(f"the session has no reference rate column: cannot {purpose}")
        return self.ref_dps

    def take(self, index: np.ndarray) -> Session:
        """The samples selected by a boolean mask or index array."""
        return Session(
            time_s=self.time_s[index],
            raw=self.raw[index],
            ref_dps=None if self.ref_dps is None else self.ref_dps[index],
            aux={name: values[index] for name, values in self.aux.items()},
            meta=dict(self.meta),
            settled=None if self.settled is None else self.settled[index],
            rail=self.rail,
            means=None if self.means is None else self.means.take(index),
        )
