"""Calibrating a triad: three sessions in, one IMU set and the figures to trust it out.

Pure: no files, no printing. Each axis's model comes from :func:`canical.calibration.pipeline.calibrate` on
its own session's own channel (unchanged); every session's plateaus are then reduced to the true
rate vector and the three per-axis corrected rates, and the coupling is fitted on the single-axis
sessions' plateaus (:mod:`canical.calibrate.coupling`, which says which estimation and why).

Then a joint refit, kept while it helps: each axis's model is fitted again, by the same pipeline,
on its channel of *all* single-axis sessions, the other sessions' plateaus with the rate the
coupling says that axis senses there (a few deg/s: exactly where the coupling is read, and where
the own session has few plateaus); the coupling is fitted again through the new models. A refit
is kept when it lowers the held-out coupled plateau error of the single-axis sessions by 2 %
(the refitted models have seen those plateaus, so the multi-axis session, never fitted, is the
honest judge), at most three times.

Held-out errors, per axis, before (today's per-axis models alone) and after (the IMU set): on the
single-axis sessions each plateau is corrected with the coupling fitted without it (leave one
plateau out; the per-axis models are not refitted); a multi-axis session (``# axis: multi``)
is never fitted, so all its plateaus are held out.
"""

from __future__ import annotations

import datetime as dt
from collections.abc import Sequence
from dataclasses import dataclass

import numpy as np

from canical.calibrate.coupling import CouplingFit, fit_coupling, held_out_corrected
from canical.calibrate.plateaus import Plateaus
from canical.calibration.imu_calibration_report import AxisModel, ImuReport, SessionErrors
from canical.calibration.pipeline import (
    CalibrateOptions,
    CalibrationResult,
    ProgressFn,
    calibrate,
    find_plateaus,
)
from canical.sessions.session import RAW_UNITS, Session
from canical.sessions.triad_session import AXES, TriadSession, check_axes_covered
from canical.sets.coefficients import DEFAULT_RAW_UNITS, CoefficientSet
from canical.sets.corrector import Corrector
from canical.sets.imu_set import ImuSet, as_matrix, check_coupling
from canical.sets.term_kinds import TIME_INPUT


def _quiet(_: str) -> None:
    pass


@dataclass(frozen=True)
class PlateauRates:
    """One session's plateaus: true rate vectors and the per-axis corrected rates, (k, 3) each."""

    true_dps: np.ndarray
    per_axis_dps: np.ndarray


@dataclass(frozen=True)
class ImuCalibration:
    """What a triad calibration produced."""

    imu_set: ImuSet
    axes: tuple[CalibrationResult, CalibrationResult, CalibrationResult]
    coupling: CouplingFit
    errors: tuple[SessionErrors, ...]
    joint_refits: int = 0

    def report(self, sources: Sequence[str], output: str) -> ImuReport:
        """The report: coupling with standard errors, errors per session and axis."""
        return ImuReport(
            sessions=tuple(sources), coefficients=output, joint_refits=self.joint_refits,
            matrix=self.coupling.matrix, standard_errors=self.coupling.standard_errors,
            coupling_plateaus=self.coupling.points, held_out=self.errors,
            axes=(axis_model(self.axes[0]), axis_model(self.axes[1]), axis_model(self.axes[2])))


def axis_model(result: CalibrationResult) -> AxisModel:
    """An axis's line in the triad's report."""
    report = result.report
    return AxisModel(report.spec, report.held_out.rms_dps, tuple(e.name for e in report.effects))


MAX_REFITS = 3
REFIT_GAIN = 0.02  # a refit is kept when it lowers the held-out coupled error by at least 2 %


@dataclass(frozen=True)
class Estimate:
    """Per-axis models, every session's plateau rates through them, and the coupling fitted on them."""

    results: tuple[CalibrationResult, CalibrationResult, CalibrationResult]
    tables: tuple[PlateauRates, ...]  # one per session, in the order given
    fit: CouplingFit
    true_dps: np.ndarray  # single-axis sessions' plateaus, stacked
    held_out_dps: np.ndarray  # each of those plateaus corrected with a coupling fitted without it

    @property
    def held_out_rms_dps(self) -> float:
        return float(np.sqrt(np.mean((self.held_out_dps - self.true_dps) ** 2)))


def model_errors(results: Sequence[CalibrationResult]) -> np.ndarray:
    """Each axis's rate model's held-out rms (after the closed loop where it ran), deg/s."""
    out = []
    for r in results:
        loop = r.report.closed_loop
        out.append(loop.held_out_rms_after_dps if loop is not None else r.report.held_out.rms_dps)
    return np.asarray(out, dtype=float)


def estimate(sessions: Sequence[TriadSession], results: Sequence[CalibrationResult],
             options: CalibrateOptions) -> Estimate:
    """The coupling on the single-axis sessions' plateaus through the given per-axis models."""
    sets = [r.coefficients for r in results]
    tables = tuple(plateau_rates(s, sets, options) for s in sessions)
    single = [t for s, t in zip(sessions, tables, strict=True) if s.table_axis is not None]
    true = np.vstack([t.true_dps for t in single])
    per_axis = np.vstack([t.per_axis_dps for t in single])
    fit = fit_coupling(true, per_axis, model_errors(results))
    check_coupling(fit.matrix, "coupling")
    held_out = held_out_corrected(true, per_axis)
    return Estimate((results[0], results[1], results[2]), tables, fit, true, held_out)


def decoupled_session(index: int, sessions: Sequence[TriadSession], sensed: np.ndarray) -> Session:
    """Channel ``index`` of every single-axis session, one after the other, its reference the rate
    that axis senses by the coupling found so far (its own session: the table's rate, which keeps
    the per-axis scale where step 1 put it). Auxiliary channels all sessions have are kept."""
    ordered = sorted((s for s in sessions if s.table_axis is not None),
                     key=lambda s: s.table_axis is None or s.table_axis.index != index)
    common = set.intersection(*(set(s.aux) for s in ordered))
    times, raws, refs = [], [], []
    offset = 0.0
    for s in ordered:
        own = s.table_axis is not None and s.table_axis.index == index
        refs.append(s.rate_dps[:, index] if own else s.rate_dps @ sensed[index])
        times.append(s.time_s - s.time_s[0] + offset)
        raws.append(s.raw[:, index])
        offset = float(times[-1][-1]) + 1.0
    aux = {name: np.concatenate([s.aux[name] for s in ordered]) for name in sorted(common)}
    meta = {**{k: v for k, v in ordered[0].meta.items() if k != "axis"}, "axis": AXES[index]}
    return Session(np.concatenate(times), np.concatenate(raws), np.concatenate(refs), aux, meta)


def calibrate_imu(sessions: Sequence[TriadSession], options: CalibrateOptions, *, sensor_id: str,
                  progress: ProgressFn = _quiet) -> ImuCalibration:
    """Per-axis models, the coupling from all single-axis sessions, refits while they help, and the
    held-out errors (before: today's per-axis models alone; after: the IMU set written)."""
    check_axes_covered(sessions)
    own = {s.table_axis.index: s for s in sessions if s.table_axis is not None}
    # A CAN log's raw values are its signal's physical value: each axis's set says in which unit,
    # or the daemon (rightly) refuses a set "in counts" on a deg/s signal.
    units = [own[i].meta.get(RAW_UNITS, DEFAULT_RAW_UNITS) for i in range(len(AXES))]
    results = []
    for i, name in enumerate(AXES):
        progress(f"axis {name}: calibrating channel raw_{name} on {own[i].source}")
        results.append(calibrate(own[i].axis_session(i), options, sensor_id=sensor_id, axis=name,
                                 raw_units=units[i]))
    first = best = estimate(sessions, results, options)
    progress(f"coupling: least squares on {first.fit.points} plateaus, held-out rms "
             f"{first.held_out_rms_dps:.4f} deg/s")
    refits = 0
    for _ in range(MAX_REFITS):
        refit = [calibrate(decoupled_session(i, sessions, best.fit.sensed), options, sensor_id=sensor_id,
                           axis=name, raw_units=units[i]) for i, name in enumerate(AXES)]
        candidate = estimate(sessions, refit, options)
        progress(f"joint refit: held-out rms {candidate.held_out_rms_dps:.4f} deg/s")
        if candidate.held_out_rms_dps > (1.0 - REFIT_GAIN) * best.held_out_rms_dps:
            break
        best, refits = candidate, refits + 1
    errors = []
    start = 0
    for s, before, after in zip(sessions, first.tables, best.tables, strict=True):
        if s.table_axis is None:
            corrected = after.per_axis_dps @ best.fit.matrix.T
        else:
            corrected = best.held_out_dps[start:start + after.true_dps.shape[0]]
            start += after.true_dps.shape[0]
        errors.append(session_errors(s, before, corrected))
    fit = best.fit
    rms = np.sqrt(np.mean((best.held_out_dps - best.true_dps) ** 2, axis=0))
    imu = ImuSet(
        sensor_id=sensor_id,
        axes=(best.results[0].coefficients, best.results[1].coefficients, best.results[2].coefficients),
        coupling=as_matrix(fit.matrix),
        coupling_se=as_matrix(fit.standard_errors),
        fit={"coupling_plateaus": fit.points, "joint_refits": refits,
             "held_out_rms_after_dps": [float(v) for v in rms]},
        created=dt.datetime.now(dt.UTC).strftime("%Y-%m-%dT%H:%M:%SZ"),
    )
    return ImuCalibration(imu, best.results, fit, tuple(errors), refits)


def session_errors(session: TriadSession, table: PlateauRates, after: np.ndarray) -> SessionErrors:
    """``table``'s per-axis rates (before) and ``after`` against the truth, rms per axis."""
    before_e = table.per_axis_dps - table.true_dps
    after_e = after - table.true_dps

    def rms(e: np.ndarray) -> tuple[float, float, float]:
        r = np.sqrt(np.mean(e**2, axis=0))
        return float(r[0]), float(r[1]), float(r[2])

    return SessionErrors(session.source, session.axis_label, int(table.true_dps.shape[0]), rms(before_e),
                         rms(after_e), float(np.max(np.abs(after_e))))


def session_plateaus(session: TriadSession, options: CalibrateOptions) -> Plateaus | np.ndarray:
    """A single-axis session's plateaus on its table axis; a multi-axis session's as a label per
    sample: steady on all three axes at once (the intersection of each axis's plateaus)."""
    if session.table_axis is not None:
        return find_plateaus(session.axis_session(session.table_axis.index), options)
    labels = np.column_stack([find_plateaus(session.axis_session(j), options).label for j in range(3)])
    steady = (labels >= 0).all(axis=1)
    key = np.where(steady, labels[:, 0] * 1_000_000 + labels[:, 1] * 1_000 + labels[:, 2], -1)
    # Renumber the runs in time order: a new plateau wherever the key changes.
    change = np.concatenate([[True], key[1:] != key[:-1]])
    label = np.cumsum(change) - 1
    return np.where(steady, label, -1)


def plateau_rates(session: TriadSession, sets: Sequence[CoefficientSet],
                  options: CalibrateOptions) -> PlateauRates:
    """Plateau means of the true rate and of each channel corrected by its own axis's set.

    Raw values, time and auxiliary channels are averaged per plateau and corrected as samples, as
    :func:`canical.calibration.evaluation.held_out_set_errors` judges a single-axis set.
    """
    found = session_plateaus(session, options)
    groups = _groups(found, session, options)

    def mean(values: np.ndarray) -> np.ndarray:
        return np.array([float(np.mean(values[g])) for g in groups])

    inputs = {name: mean(v) for name, v in session.aux.items()}
    inputs[TIME_INPUT] = mean(session.time_s)
    true = np.column_stack([mean(session.rate_dps[:, j]) for j in range(3)])
    per_axis = np.column_stack([Corrector(c).correct(mean(session.raw[:, j]), inputs)[0]
                                for j, c in enumerate(sets)])
    return PlateauRates(true, per_axis)


def _groups(found: Plateaus | np.ndarray, session: TriadSession,
            options: CalibrateOptions) -> list[np.ndarray]:
    """Sample indices of each plateau (multi-axis runs shorter than the minimum plateau left out)."""
    if isinstance(found, Plateaus):
        return [np.arange(a, b) for a, b in zip(found.start, found.stop, strict=True)]
    dt_s = float(np.median(np.diff(session.time_s))) if len(session) > 1 else 1.0
    shortest = max(2, int(options.min_duration_s / dt_s))
    groups = [np.flatnonzero(found == k) for k in np.unique(found[found >= 0])]
    return [g for g in groups if g.size >= shortest]

