"""A grid of rate-table behaviours, and how calibration fares on each against an ideal table.

Each cell records the same sensor (same seed, so the same noise) through one
:class:`canical.sim.table_recording.TableBehaviour` and calibrates it with the default
model. A cell passes when every scheduled plateau is found (count and rates), no used sample
lies on a rate change (the table's truth is known here), and the held-out error, pooled over
seeds, is within a factor of the same sensors recorded on an ideal table (instantaneous
steps, the commanded rate with every sample).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import TypedDict

import numpy as np

from canical.calibrate.plateaus import Plateaus
from canical.calibration.pipeline import CalibrateOptions, CalibrationResult, calibrate
from canical.sessions.session import Session
from canical.sim.gyro import GyroModel
from canical.sim.sessions import paper_rates, recorded_sweep
from canical.sim.table_recording import Schedule, TableBehaviour, TableRecording

IDEAL = TableBehaviour()
class _MeasuredReference(TypedDict):
    """A measured reference's settings, shared by the combined cells."""

    reference: str
    jitter_dps: float
    encoder_lsb_dps: float


MEASURED_02: _MeasuredReference = {"reference": "measured", "jitter_dps": 0.02, "encoder_lsb_dps": 0.001}

GRID: tuple[tuple[str, TableBehaviour], ...] = (
    ("ideal steps", IDEAL),
    ("ramp 1 deg/s²", TableBehaviour(accel_dps2=1.0)),
    ("ramp 3 deg/s²", TableBehaviour(accel_dps2=3.0)),
    ("ramp 10 deg/s²", TableBehaviour(accel_dps2=10.0)),
    ("ramp 100 deg/s²", TableBehaviour(accel_dps2=100.0)),
    ("S-curve 10 deg/s², 20 deg/s³", TableBehaviour(accel_dps2=10.0, jerk_dps3=20.0)),
    ("overshoot 10% ringing 2 Hz", TableBehaviour(accel_dps2=100.0, overshoot=0.1)),
    ("measured, jitter 0.01", TableBehaviour(reference="measured", jitter_dps=0.01)),
    ("measured, jitter 0.05", TableBehaviour(reference="measured", jitter_dps=0.05)),
    ("reference 10 Hz held", TableBehaviour(accel_dps2=10.0, ref_rate_hz=10.0)),
    ("reference 10 Hz asynchronous, 30 ms late",
     TableBehaviour(accel_dps2=10.0, ref_rate_hz=10.0, asynchronous=True, ref_latency_s=0.03)),
    ("3% rows lost in bursts", TableBehaviour(accel_dps2=10.0, loss_fraction=0.03)),
    ("ramp 1 + measured 0.02 + 10 Hz async",
     TableBehaviour(accel_dps2=1.0, ref_rate_hz=10.0, asynchronous=True, **MEASURED_02)),
    ("S-curve + overshoot + measured 0.02 + lost 3%",
     TableBehaviour(accel_dps2=3.0, jerk_dps3=5.0, overshoot=0.1, loss_fraction=0.03, **MEASURED_02)),
    ("ramp 3 + overshoot + measured 0.02 + 10 Hz async + late + lost 3% + settled flag",
     TableBehaviour(accel_dps2=3.0, overshoot=0.1, ref_rate_hz=10.0, asynchronous=True, ref_latency_s=0.03,
                    loss_fraction=0.03, settled_flag=True, **MEASURED_02)),
)

#: Beyond the grid: a measured reference with 0.05 deg/s jitter sent at 10 Hz carries ten times
#: fewer independent values than at 100 Hz; the table's own rate is then known to about
#: 0.05/√(10 Hz · plateau seconds) deg/s, and that limits any calibration from it.
HARSH: tuple[tuple[str, TableBehaviour], ...] = (
    ("everything, measured 0.05 at 10 Hz",
     TableBehaviour(accel_dps2=3.0, overshoot=0.1, reference="measured", jitter_dps=0.05,
                    encoder_lsb_dps=0.001, ref_rate_hz=10.0, asynchronous=True, ref_latency_s=0.03,
                    loss_fraction=0.03, settled_flag=True)),
)


@dataclass(frozen=True)
class CellResult:
    """One cell of the grid."""

    name: str
    scheduled: int
    found: int
    rates_ok: bool  # every scheduled rate found, in order, within its tolerance
    ramp_samples_used: int  # used samples that lie on a rate change (truth known)
    held_out_rms_dps: float
    ideal_rms_dps: float
    used: int
    total: int
    ref_noise_dps: float
    rate_tol_dps: float

    @property
    def ratio(self) -> float:
        return self.held_out_rms_dps / self.ideal_rms_dps

    def passes(self, max_ratio: float = 1.3) -> bool:
        return (self.found == self.scheduled and self.rates_ok and self.ramp_samples_used == 0
                and self.ratio <= max_ratio)


def grid_rates() -> np.ndarray:
    """The paper's protocol, −60…60 deg/s in 3 deg/s steps, ascending."""
    return paper_rates()


def held_out_rms(behaviour: TableBehaviour, *, seed: int, dwell_s: float, fs_hz: float,
                 gyro: GyroModel | None = None,
                 rates: np.ndarray | None = None
                 ) -> tuple[float, CalibrationResult, tuple[Session, TableRecording]]:
    """Calibrate one recording; (held-out rms, the calibration result, the table's truth)."""
    rates = grid_rates() if rates is None else rates
    session, rec = recorded_sweep(gyro or GyroModel(), rates, behaviour, dwell_s=dwell_s,
                                  fs_hz=fs_hz, seed=seed)
    result = calibrate(session, CalibrateOptions(extend=False), sensor_id="SIM", axis="z")
    return float(result.report.held_out.rms_dps), result, (session, rec)


def score_cell(name: str, behaviour: TableBehaviour, *, seed: int = 0, dwell_s: float = 5.0,
               fs_hz: float = 100.0, ideal_rms: float | None = None) -> CellResult:
    """Run one cell against the ideal table with the same sensor and seed."""
    if ideal_rms is None:
        ideal_rms = held_out_rms(IDEAL, seed=seed, dwell_s=dwell_s, fs_hz=fs_hz)[0]
    rms, result, (session, rec) = held_out_rms(behaviour, seed=seed, dwell_s=dwell_s, fs_hz=fs_hz)
    p = result.base.plateaus
    sched = rec.schedule
    found_ok = p.count == sched.rates.size
    tol = np.maximum(0.05, 5 * p.rate_uncertainty())
    rates_ok = found_ok and bool(np.all(np.abs(p.rate_dps - sched.rates) <= tol))
    ramp_rows = rows_on_rate_changes(p, sched, rec.time_s[rec.kept])
    return CellResult(
        name=name,
        scheduled=int(sched.rates.size),
        found=p.count,
        rates_ok=rates_ok,
        ramp_samples_used=ramp_rows,
        held_out_rms_dps=rms,
        ideal_rms_dps=ideal_rms,
        used=p.n_used,
        total=len(session),
        ref_noise_dps=p.ref_noise_dps,
        rate_tol_dps=p.rate_tol_dps,
    )


def rows_on_rate_changes(p: Plateaus, sched: Schedule, ticks: np.ndarray, eps: float = 1e-9) -> int:
    """How many used rows lie off the plateau they were given (on a rate change), by the truth.

    ``ticks`` are the rows' true instants; a plateau spans [end of its rate change, start of
    the next], both instants at its rate; ``eps`` is how far a recorded time may be off.
    """
    used = p.label >= 0
    t = ticks[used]
    if p.count == sched.rates.size:
        j = p.label[used]
        on_ramp = (t < sched.end[j] - eps) | (t > sched.stop[j] + eps)
    else:  # match each used row to the plateau its tick lies on
        k = np.searchsorted(sched.start, t - eps, side="right") - 1
        on_ramp = t < sched.end[np.clip(k, 0, None)] - eps
    return int(on_ramp.sum())


SEEDS = (0, 1, 2, 3, 4)
DWELL_S = 8.0
FS_HZ = 100.0


def ideal_rms(seeds=SEEDS, dwell_s: float = DWELL_S, fs_hz: float = FS_HZ) -> dict[int, float]:
    """Held-out rms of each seed's sensor on the ideal table."""
    return {s: held_out_rms(IDEAL, seed=s, dwell_s=dwell_s, fs_hz=fs_hz)[0] for s in seeds}


def score_over_seeds(name: str, behaviour: TableBehaviour, ideal: dict[int, float],
                     dwell_s: float = DWELL_S, fs_hz: float = FS_HZ) -> list[CellResult]:
    """One cell for every seed of ``ideal`` (the same sensors as on the ideal table)."""
    return [score_cell(name, behaviour, seed=s, dwell_s=dwell_s, fs_hz=fs_hz, ideal_rms=r)
            for s, r in ideal.items()]


def pooled_ratio(results: list[CellResult]) -> float:
    """Held-out rms over all seeds' plateaus, relative to the same sensors on the ideal table.

    Each seed's sensor has the same noise at the same instants of every plateau on both
    tables (:mod:`canical.sim.paired_noise`), so one seed's ratio is a paired comparison
    (ramps alone: 0.99-1.03 per seed, where unpaired draws scattered 0.5-1.8). What still
    varies per seed: the table's own draw (a measured reference's jitter, which rows are
    lost) and the segment points the fit places at extrema of the data: seed 4 on the ideal
    table finds an extremum at -21 deg/s (5 segments, held-out 0.0052 deg/s) that a few rows
    fewer leave below the prominence threshold (4 segments, 0.0109), a ratio of 2 that asking
    for 5 segments does not remove (the points are found, not given). Pooled over seeds the
    comparison measures the table, not those draws.
    """
    cell = np.sqrt(np.mean([r.held_out_rms_dps**2 for r in results]))
    ideal = np.sqrt(np.mean([r.ideal_rms_dps**2 for r in results]))
    return float(cell / ideal)
