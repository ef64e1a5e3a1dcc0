"""A turntable session whose table recorded its rate to its own file, on its own clock.

The sensor's noise is drawn sample by sample here, not tied to plateau instants
(:mod:`canical.sim.paired_noise`): that pairing holds one noise sample through each ramp,
which shifts a whole ramp by a constant, exactly what an aligner reads as a time shift.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from canical.sessions.reference_clock import ClockFit, TableTrace
from canical.sessions.session import Session
from canical.sim.gyro import GyroModel
from canical.sim.sessions import paper_rates
from canical.sim.table_recording import TableBehaviour, record_table


@dataclass(frozen=True)
class OwnClockCase:
    session: Session  # the sensor's log: no reference
    table: TableTrace  # the table's file, on its own clock
    truth: ClockFit  # the table's clock against the session's


def own_clock_case(seed: int, *, accel_dps2: float | None = None, ref_rate_hz: float = 10.0,
                   offset_s: float = 1234.5, drift_ppm: float = 80.0, gyro: GyroModel | None = None,
                   rates: np.ndarray | None = None, dwell_s: float = 10.0,
                   fs_hz: float = 200.0) -> OwnClockCase:
    """The table's frames at ``ref_rate_hz`` on a clock ``offset_s + (1 + drift_ppm·1e-6)·t``."""
    behaviour = TableBehaviour(accel_dps2=accel_dps2, ref_rate_hz=ref_rate_hz, asynchronous=True)
    rec = record_table(paper_rates() if rates is None else rates, dwell_s=dwell_s, fs_hz=fs_hz,
                       behaviour=behaviour, rng=np.random.default_rng(seed + 1))
    gyro = gyro or GyroModel()
    raw = gyro.output(rec.time_s, rec.true_dps, rng=np.random.default_rng(seed), fs_hz=fs_hz)
    session = Session(rec.time_s, raw, None, {}, {"sensor": "SIM-0001", "axis": "z"})
    truth = ClockFit(offset_s, drift_ppm, 0, 0, 0.0, 0.0)
    table = TableTrace(truth.to_table(rec.frame_time_s), rec.frame_dps, "table.csv")
    return OwnClockCase(session, table, truth)


def table_csv(table: TableTrace) -> str:
    """The table's file as a table controller might write it: its own times and rate."""
    rows = "\n".join(f"{t:.6f},{r:.4f}" for t, r in zip(table.time_s, table.ref_dps, strict=True))
    return f"time_s,ref_dps\n{rows}\n"
