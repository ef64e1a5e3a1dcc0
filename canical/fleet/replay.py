"""Recorded raw drives replayed through two generations of sets and the bias tracker
(``fleet replay``): the zero-rate error at standstills and the heading drift, before and after.

Why block by block: a drive is read a block of rows at a time (CSV through the reader ``apply``
uses, Parquet a row group batch at a time), each block corrected by each generation's set
(:meth:`~canical.sets.corrector.Corrector.correct_next` carries the terms' state) and fed to
that generation's tracker (:class:`~canical.tracking.replay.Replayer` carries its state), so a
worker holds one block, not a drive, and any cut into blocks gives the same numbers.

Why these figures: at a standstill the true rate is zero, so the output is the error. Two
figures per standstill, each a mean over its rows (the noise averages out):

- *carried into it*: the output less the bias the tracker applied at its first row. That is the
  error the vehicle carried into the stop, what the tracker had not caught up with, before it
  re-learns the bias there: the temperature slope the set leaves over times the warming since the
  last stop, less what the tracker's own slope predicted. This is the error a set is responsible
  for;
- *with the tracked bias*: the output less the bias tracked row by row. Within the stop the
  tracker learns the bias again (after three still windows, then slewing to it), so this mixes
  the carried error with the tracker's re-learning and its own noise floor; kept as it was.

The carried figure is a mean over the stop's rows, so its square is, on average, the error
squared plus the variance of that mean: the standstill's own noise (white noise and the engine's
idle vibration), which no set removes. That variance is estimated from the stop itself
(:mod:`canical.fleet.stop_noise`: its one-second means, about a line), so a third figure, the
carried error less its own noise, needs no truth: what a fleet engineer reads to tell what a new
set changed from what no set can.

Standstills shorter than :data:`MIN_STOP_S` are left out (a speed that touches zero for a row),
and so is the first standstill of each power-on: there the error is the new turn-on bias, which
no set knows and the tracker learns at that very stop.
The heading drift is the output less the true rate (a ``true_rate_dps`` column, as a simulated
drive has), else less zero at the standstills only, integrated over the drive, in degrees.
"""

from __future__ import annotations

import itertools
import math
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from canical.errors import CanicalError
from canical.fleet.drive_log import LogLayout, log_blocks
from canical.fleet.stop_noise import MeanNoise, StopSeconds
from canical.sessions.canlog_format import is_canlog
from canical.sessions.csv_chunks import read_chunks, read_head
from canical.sets import coefficient_file
from canical.sets.coefficients import CoefficientSet
from canical.sets.corrector import Corrector
from canical.tracking.config import TrackerConfig
from canical.tracking.replay import Replayer

CUE, CUE_BELOW, TEMP, TRUTH = "speed_mps", 0.1, "temp_c", "true_rate_dps"
NEEDED = ("time_s", "raw", CUE)
#: A standstill shorter than this is a dip of the speed (a ramp's last row), not a stop.
MIN_STOP_S = 5.0
#: Rows per Parquet batch (a CSV block is the reader's, 256 KiB).
PARQUET_ROWS = 65_536


@dataclass(frozen=True)
class DriveTask:
    """One drive to replay: where it is, its vehicle, and the two generations' set files."""

    drive: str
    vehicle_id: str
    sensor_id: str
    baseline: str
    new: str
    layout: LogLayout | None = None  # how to read it, when it is a CAN log


@dataclass(frozen=True)
class Generation:
    """One generation's figures over one drive (or, summed, a vehicle's drives)."""

    stops: int  # standstills judged (each power-on's first left out)
    error_sq: float  # sum over them of the squared mean error, (deg/s)²
    heading_sq: float  # sum over drives of the squared heading drift, deg²
    drives: int
    carried_sq: float = 0.0  # sum over them of the squared error carried in (the bias as they began)
    #: sum over them of their carried mean's own noise: its variance, estimated from the stop
    carried_noise_sq: float = 0.0
    #: the variance that noise leaves in ``carried_sq - carried_noise_sq`` (its uncertainty²)
    less_noise_var: float = 0.0

    @property
    def zero_rate_rms_dps(self) -> float:
        return math.sqrt(self.error_sq / self.stops) if self.stops else math.nan

    @property
    def carried_rms_dps(self) -> float:
        return math.sqrt(self.carried_sq / self.stops) if self.stops else math.nan

    @property
    def carried_noise_rms_dps(self) -> float:
        """The standstills' own noise in the carried figure, RMS (the part no set removes)."""
        return math.sqrt(self.carried_noise_sq / self.stops) if self.stops else math.nan

    @property
    def carried_less_noise_dps(self) -> float:
        """The carried error less the standstills' own noise, RMS; 0 when the noise is all of it
        (the sum is unbiased and may fall below 0: floored here, where it is reported)."""
        return self._less_noise_rms(0.0)

    @property
    def carried_less_noise_sd_dps(self) -> float:
        """Its 1σ as the noise leaves it: how far its +1σ bound lies above it (near 0 the figure
        is only known to be below that bound)."""
        return self._less_noise_rms(math.sqrt(self.less_noise_var)) - self._less_noise_rms(0.0)

    def _less_noise_rms(self, plus: float) -> float:
        if not self.stops:
            return math.nan
        return math.sqrt(max(self.carried_sq - self.carried_noise_sq + plus, 0.0) / self.stops)

    @property
    def heading_rms_deg(self) -> float:
        return math.sqrt(self.heading_sq / self.drives) if self.drives else math.nan

    def plus(self, other: Generation) -> Generation:
        return Generation(self.stops + other.stops, self.error_sq + other.error_sq,
                          self.heading_sq + other.heading_sq, self.drives + other.drives,
                          self.carried_sq + other.carried_sq, self.carried_noise_sq + other.carried_noise_sq,
                          self.less_noise_var + other.less_noise_var)


@dataclass(frozen=True)
class DriveResult:
    """A drive's figures with the baseline sets and with the new ones."""

    vehicle_id: str
    sensor_id: str
    rows: int
    before: Generation
    after: Generation


class _Tally:
    """One generation's running sums over a drive's blocks: standstills (a run of stopped rows
    within a power-on), their error sums (with the tracked bias, and with the bias as the run
    began, with that mean's own noise), and the heading integral."""

    def __init__(self) -> None:
        self.last_time = math.inf  # the first row starts a power-on
        self.stopped = False
        self.first_of_power_on = True
        self.run_sum = self.run_n = self.run_start = self.run_end = 0.0
        self.run_bias_sum = self.run_first_bias = 0.0
        self.run_counts = False
        self.seconds = StopSeconds()
        self.stops, self.error_sq, self.carried_sq, self.heading = 0, 0.0, 0.0, 0.0
        self.noise = MeanNoise(0.0, 0.0)

    def block(self, time_s: np.ndarray, stop: np.ndarray, err: np.ndarray, truth: np.ndarray | None,
              bias: np.ndarray) -> None:
        prev = np.concatenate([[self.last_time], time_s[:-1]])
        new_power_on = time_s < prev
        dt = np.where(new_power_on, 0.0, time_s - prev)
        drift = err if truth is not None else np.where(stop, err, 0.0)
        self.heading += float(drift @ dt)
        self._segments(time_s, new_power_on, stop, err, bias)
        self.last_time = float(time_s[-1])

    def _segments(self, time_s: np.ndarray, new_power_on: np.ndarray, stop: np.ndarray,
                  err: np.ndarray, bias: np.ndarray) -> None:
        """Walk the block's runs (cut at each power-on and each change of stopped)."""
        was = np.concatenate([[self.stopped], stop[:-1]])
        cuts = np.flatnonzero(new_power_on | (stop != was))
        edges = [0, *cuts.tolist(), len(stop)]
        for a, b in itertools.pairwise(edges):
            if b <= a:
                continue
            if new_power_on[a] or stop[a] != self.stopped:
                self._close()
                if new_power_on[a]:
                    self.first_of_power_on = True
                self.stopped = bool(stop[a])
                if self.stopped:
                    self.run_counts, self.first_of_power_on = not self.first_of_power_on, False
                    self.run_start, self.run_first_bias = float(time_s[a]), float(bias[a])
                    self.seconds = StopSeconds(self.run_start)
            if self.stopped:
                if self.run_counts:
                    self.seconds.add(time_s[a:b], err[a:b] + bias[a:b])
                self.run_sum += float(err[a:b].sum())
                self.run_bias_sum += float(bias[a:b].sum())
                self.run_n += b - a
                self.run_end = float(time_s[b - 1])

    def _close(self) -> None:
        if self.stopped and self.run_counts and self.run_end - self.run_start >= MIN_STOP_S:
            self.stops += 1
            self.error_sq += (self.run_sum / self.run_n) ** 2
            carried = (self.run_sum + self.run_bias_sum) / self.run_n - self.run_first_bias
            self.carried_sq += carried ** 2
            self.noise = self.noise.plus(self.seconds.noise(carried))
        self.run_sum = self.run_n = self.run_bias_sum = 0.0
        self.run_counts = False

    def result(self) -> Generation:
        self._close()
        self.stopped = False
        return Generation(self.stops, self.error_sq, self.heading ** 2, 1, self.carried_sq,
                          self.noise.variance, self.noise.less_noise_var)


class _Pipeline:
    """One generation over one drive: its corrector, its tracker and its tally."""

    def __init__(self, cset: CoefficientSet) -> None:
        self.corrector = Corrector(cset)
        config = TrackerConfig(cue_threshold=CUE_BELOW).for_sets([cset.fit], arw_given=False)
        self.replayer = Replayer(config, axes=(cset.axis,))
        self.tally = _Tally()

    def block(self, cols: dict[str, np.ndarray]) -> None:
        inputs = {name: cols[name] for name in self.corrector.required_inputs if name in cols}
        rate, _ = self.corrector.correct_next(cols["raw"], inputs)
        temp = cols.get(TEMP)
        bias = self.replayer.feed(cols["time_s"], rate, temp, cols[CUE])[:, 0]
        truth = cols.get(TRUTH)
        err = rate - bias - (truth if truth is not None else 0.0)
        self.tally.block(cols["time_s"], np.abs(cols[CUE]) < CUE_BELOW, err, truth, bias)


def replay_drive(task: DriveTask) -> DriveResult:
    """One drive through both generations (a task of :func:`canical.fleet.engine.run_tasks`)."""
    before = _Pipeline(coefficient_file.load(task.baseline))
    after = _Pipeline(coefficient_file.load(task.new))
    rows = 0
    for cols in blocks(Path(task.drive), task.layout, before.corrector.cset.axis):
        rows += len(cols["time_s"])
        before.block(cols)
        after.block(cols)
    return DriveResult(task.vehicle_id, task.sensor_id, rows, before.tally.result(), after.tally.result())


def blocks(path: Path, layout: LogLayout | None = None, axis: str = "z") -> Iterator[dict[str, np.ndarray]]:
    """A drive's columns a block at a time: a CSV (the reader ``apply`` uses), Parquet, or a CAN
    log read with ``layout`` (the raw signal of ``axis``)."""
    if path.suffix == ".parquet":
        yield from _parquet_blocks(path)
        return
    if is_canlog(path):
        if layout is None:
            raise CanicalError(f"{path}: reading a CAN log needs --dbc or --config")
        yield from log_blocks(path, layout, axis, (*NEEDED, TEMP, TRUTH), NEEDED)
        return
    head = read_head(path)
    if head is None:
        raise CanicalError(f"{path}: a line break other than newline; not a drive CSV")
    missing = [c for c in NEEDED if c not in head.header]
    if missing:
        raise CanicalError(f"{path}: no column {missing[0]!r} (a drive needs {', '.join(NEEDED)})")
    wanted = [c for c in (*NEEDED, TEMP, TRUTH) if c in head.header]
    for chunk in read_chunks(head, wanted):
        yield chunk.columns


def _parquet_blocks(path: Path) -> Iterator[dict[str, np.ndarray]]:
    import pyarrow.parquet as pq

    try:
        source = pq.ParquetFile(path)
    except (OSError, ValueError) as exc:
        raise CanicalError(f"{path}: not a Parquet file ({exc})") from None
    names = source.schema_arrow.names
    missing = [c for c in NEEDED if c not in names]
    if missing:
        raise CanicalError(f"{path}: no column {missing[0]!r} (a drive needs {', '.join(NEEDED)})")
    wanted = [c for c in (*NEEDED, TEMP, TRUTH) if c in names]
    for batch in source.iter_batches(batch_size=PARQUET_ROWS, columns=wanted):
        yield {c: batch.column(c).to_numpy(zero_copy_only=False).astype(float) for c in wanted}


def drive_sensor(path: Path, layout: LogLayout | None = None) -> str | None:
    """The sensor a drive names: a CSV's ``# sensor:`` line, a Parquet file's ``sensor`` metadata,
    a CAN log's ``--sensor`` (or its configuration's)."""
    if is_canlog(path):
        return layout.sensor if layout is not None else None
    if path.suffix == ".parquet":
        import pyarrow.parquet as pq

        meta = pq.read_schema(path).metadata or {}
        value = meta.get(b"sensor")
        return value.decode() if value else None
    head = read_head(path)
    return head.meta.get("sensor") if head is not None else None


@dataclass(frozen=True)
class VehicleResult:
    """A vehicle's drives summed: before (baseline sets) and after (new sets)."""

    vehicle_id: str
    sensor_id: str
    rows: int
    before: Generation
    after: Generation


def per_vehicle(results: list[DriveResult]) -> list[VehicleResult]:
    """The drives' figures summed per vehicle, in the vehicles' order (the drives' order is fixed)."""
    out: dict[str, VehicleResult] = {}
    for r in results:
        prev = out.get(r.vehicle_id)
        if prev is None:
            out[r.vehicle_id] = VehicleResult(r.vehicle_id, r.sensor_id, r.rows, r.before, r.after)
        else:
            out[r.vehicle_id] = VehicleResult(r.vehicle_id, prev.sensor_id, prev.rows + r.rows,
                                              prev.before.plus(r.before), prev.after.plus(r.after))
    return [out[k] for k in sorted(out)]


def vehicles_csv(vehicles: list[VehicleResult]) -> str:
    """One row per vehicle: its figures before and after (``%.6g``: the same on any engine)."""
    lines = ["vehicle_id,sensor_id,drives,rows,standstills,carried_before_dps,carried_after_dps,"
             "zero_rate_before_dps,zero_rate_after_dps,heading_before_deg,heading_after_deg,"
             "carried_noise_before_dps,carried_noise_after_dps,carried_less_noise_before_dps,"
             "carried_less_noise_after_dps,carried_less_noise_before_sd_dps,carried_less_noise_after_sd_dps"]
    for v in vehicles:
        lines.append(f"{v.vehicle_id},{v.sensor_id},{v.before.drives},{v.rows},{v.before.stops},"
                     f"{v.before.carried_rms_dps:.6g},{v.after.carried_rms_dps:.6g},"
                     f"{v.before.zero_rate_rms_dps:.6g},{v.after.zero_rate_rms_dps:.6g},"
                     f"{v.before.heading_rms_deg:.6g},{v.after.heading_rms_deg:.6g},"
                     f"{v.before.carried_noise_rms_dps:.6g},{v.after.carried_noise_rms_dps:.6g},"
                     f"{v.before.carried_less_noise_dps:.6g},{v.after.carried_less_noise_dps:.6g},"
                     f"{v.before.carried_less_noise_sd_dps:.6g},{v.after.carried_less_noise_sd_dps:.6g}")
    return "\n".join(lines) + "\n"
