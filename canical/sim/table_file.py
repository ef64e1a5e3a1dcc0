"""A rate table that logs its rate to a file of its own, stamped by its own clock.

Why: many table controllers write their rate to their own file, on another epoch and with a
crystal tens of ppm off the logger's (docs/sessions.md, "a table's own file on its own clock").
``calibrate --reference`` aligns such a file to the sensor's log by the rate changes both show;
``canical simulate --table-file`` writes one beside the sensor's log, so that a user without a
table can try that path. The file's rows come at the table's own rate, with a random phase and
jittered instants, as a controller's would: never on the sensor's sample instants.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np


@dataclass(frozen=True)
class TableClock:
    """The table's clock against the logger's: table time = offset_s + (1 + drift_ppm·1e-6)·t."""

    offset_s: float = 5000.25
    drift_ppm: float = -75.0
    frame_hz: float = 10.0  # how often the controller writes a row


@dataclass(frozen=True)
class TableRows:
    """What the table's file holds: its own times and the rate it recorded at each."""

    time_s: np.ndarray
    ref_dps: np.ndarray


def table_rows(time_s: np.ndarray, ref_dps: np.ndarray, clock: TableClock, seed: int) -> TableRows:
    """The table's rows for a session whose reference at the logger's ``time_s`` is ``ref_dps``:
    each row holds the rate as of its instant, its time written on the table's clock."""
    rng = np.random.default_rng([seed, 61])
    t = np.asarray(time_s, dtype=float)
    period = 1.0 / clock.frame_hz
    instants = t[0] + rng.uniform(0, period) + np.arange(int((t[-1] - t[0]) / period)) * period
    instants = np.sort(instants + rng.uniform(-0.1, 0.1, instants.size) * period)
    latest = np.clip(np.searchsorted(t, instants, side="right") - 1, 0, None)
    own = clock.offset_s + (1.0 + clock.drift_ppm * 1e-6) * instants
    return TableRows(own, np.asarray(ref_dps, dtype=float)[latest])


def table_csv(rows: TableRows) -> str:
    """The file as a table controller might write it (what ``--reference`` reads by default)."""
    lines = "".join(f"{t:.6f},{r:.4f}\n" for t, r in zip(rows.time_s, rows.ref_dps, strict=True))
    return "time_s,ref_dps\n" + lines
