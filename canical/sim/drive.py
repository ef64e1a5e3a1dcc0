"""Simulated drives for the bias tracker: stops, turns, creep, power cycles, a warming cabin.

Why these pieces: each is a way a tracker can go wrong. Stops with the engine idling shake
the gyro (a stop must still be recognised); a long steady turn is as quiet as a stop (it must
never be learned as a bias); creep in traffic is slow and smooth (with a speed cue nothing may
be learned from it); a short stop tests how fast a bias is learned; a power cycle brings a new
turn-on bias; the cabin warming from 20 to 45 °C moves the bias by its temperature slope
between stops.

The rate written is what the table calibration gives: the true rate plus the bias it never saw
(turn-on bias, temperature drift, a slow wander), white noise and vibration. Time is time since
power-on, so it starts again at each power cycle, as a recorded drive's would.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy.signal import lfilter

from canical.tracking.events import TakenWindow

STOP, DRIVE, TURN, CREEP = "stop", "drive", "turn", "creep"
#: The slowest a car drives between its ramps (m/s); creep and stops are their own segments.
MIN_DRIVE_MPS = 2.0


@dataclass(frozen=True)
class DriveModel:
    """The car, the cabin and the sensor on it."""

    rate_hz: float = 100.0
    first_turn_on_dps: float = 0.35  # the first power-on's bias the table never saw
    turn_on_spread_dps: float = 0.35  # later power-ons: uniform in ±[0.3, 1] x this
    temp_slope_dps_per_c: float = 0.012
    cabin_start_c: float = 20.0
    cabin_end_c: float = 45.0
    cabin_tau_s: float = 400.0
    #: Where the temperature slope's bias is zero: None, the cabin's start (a drive judged on
    #: its own); a fleet's drive gives the 25 °C its field log and proposed sets state it at.
    slope_reference_c: float | None = None
    white_dps: float = 0.05  # per sample
    idle_vibration_dps: float = 0.15  # amplitude of the engine's firing vibration at idle
    road_vibration_dps: float = 0.2  # rms while moving
    bias_walk_dps_rt_s: float = 2e-5
    turn_dps: float = 15.0
    turn_hold_s: float = 40.0
    off_s: float = 60.0  # power off between cycles (the cabin keeps warming)


@dataclass(frozen=True)
class Drive:
    """A simulated drive, one row per sample."""

    time_s: np.ndarray  # since power-on (restarts at each power cycle)
    clock_s: np.ndarray  # since the drive began (power-off gaps included)
    rate_dps: np.ndarray  # what the table's set gives
    true_rate_dps: np.ndarray
    bias_dps: np.ndarray  # the true bias in rate_dps (without noise and vibration)
    temp_c: np.ndarray
    speed_mps: np.ndarray
    segment: np.ndarray  # STOP, DRIVE, TURN or CREEP per row
    cycle: np.ndarray  # power cycle per row
    rate_hz: float

    def mask(self, kind: str) -> np.ndarray:
        return self.segment == kind

    @property
    def moving(self) -> np.ndarray:
        return self.segment != STOP


def plan(rng: np.random.Generator) -> list[list[tuple[str, float]]]:
    """Three power-ons of segments, durations jittered: about 16 minutes switched on."""
    def j(seconds: float) -> float:
        return float(seconds * rng.uniform(0.75, 1.25))

    turn = (TURN, 0.0)  # its length is set by the model
    cycles = [
        [(STOP, j(20)), (DRIVE, j(70)), (STOP, j(15)), (DRIVE, j(50)), turn, (DRIVE, j(40)),
         (CREEP, j(60)), (STOP, 8.0), (DRIVE, j(80)), (STOP, j(25))],
        [(STOP, j(15)), (DRIVE, j(90)), (STOP, j(20)), (CREEP, j(45)), (STOP, 8.0), (DRIVE, j(60)),
         turn, (DRIVE, j(40)), (STOP, j(15))],
        [(STOP, j(15)), (DRIVE, j(100)), (STOP, j(12)), (DRIVE, j(60)), (CREEP, j(40)), (STOP, j(20))],
    ]
    return cycles


def _smooth(rng: np.random.Generator, n: int, fs: float, cutoff_hz: float, rms: float) -> np.ndarray:
    """Gaussian noise low-passed (first order, twice) and scaled to an rms."""
    a = np.exp(-2 * np.pi * cutoff_hz / fs)
    x = lfilter([1 - a], [1, -a], lfilter([1 - a], [1, -a], rng.standard_normal(n + int(5 * fs))))
    x = x[int(5 * fs):]
    return np.asarray(x / (np.std(x) or 1.0) * rms)


def _envelope(n: int, fs: float, ramp_s: float) -> np.ndarray:
    """0 → 1 → 0 with raised-cosine ramps: moving starts and ends at rest."""
    k = min(int(ramp_s * fs), n // 2)
    env = np.ones(n)
    if k > 0:
        up = 0.5 - 0.5 * np.cos(np.linspace(0, np.pi, k))
        env[:k] = up
        env[n - k:] = up[::-1]
    return env


def _segment(kind: str, seconds: float, model: DriveModel, rng: np.random.Generator,
             ) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """(true yaw rate, speed, vibration) of one segment."""
    fs = model.rate_hz
    if kind == TURN:
        seconds = model.turn_hold_s + 6.0
    n = round(seconds * fs)
    t = np.arange(n) / fs
    if kind == STOP:
        f = rng.uniform(22.0, 30.0)  # idle firing frequency
        vib = model.idle_vibration_dps * np.sin(2 * np.pi * f * t + rng.uniform(0, 2 * np.pi))
        return np.zeros(n), np.zeros(n), vib
    vib = model.road_vibration_dps * rng.standard_normal(n)
    if kind == TURN:
        env = _envelope(n, fs, 3.0)
        sign = rng.choice([-1.0, 1.0])
        return sign * model.turn_dps * env, 12.0 * np.ones(n), vib
    if kind == CREEP:
        env = _envelope(n, fs, 2.0)
        speed = (0.6 + 0.5 * np.abs(_smooth(rng, n, fs, 0.1, 1.0))) * env + 0.3 * (env > 0)
        return _smooth(rng, n, fs, 0.1, 0.4) * env, speed, vib
    env = _envelope(n, fs, 3.0)
    # the wander is floored: a car driving never shows a speed below MIN_DRIVE_MPS (a wander of
    # -3σ once gave seconds of negative speed, read as a standstill while the car was turning)
    cruise = np.maximum(12.0 + 4.0 * _smooth(rng, n, fs, 0.02, 1.0), MIN_DRIVE_MPS)
    speed = cruise * env + 0.3 * (env > 0)
    return _smooth(rng, n, fs, 0.3, 5.0) * env, speed, vib


def simulate_drive(seed: int, model: DriveModel | None = None) -> Drive:
    """One drive: the plan's segments for each power-on, the cabin warming throughout."""
    model = model or DriveModel()
    rng = np.random.default_rng(seed)
    fs = model.rate_hz
    cols: dict[str, list[np.ndarray]] = {k: [] for k in
                                          ("time", "clock", "true", "speed", "vib", "seg", "cycle", "on")}
    clock = 0.0
    for c, segments in enumerate(plan(rng)):
        if c == 0:
            turn_on = model.first_turn_on_dps
        else:
            turn_on = float(rng.choice([-1.0, 1.0]) * rng.uniform(0.3, 1.0) * model.turn_on_spread_dps)
        parts = [_segment(kind, seconds, model, rng) for kind, seconds in segments]
        n = sum(len(p[0]) for p in parts)
        time = np.arange(n) / fs
        cols["time"].append(time)
        cols["clock"].append(clock + time)
        for (kind, _), (true, speed, vib) in zip(segments, parts, strict=True):
            cols["true"].append(true)
            cols["speed"].append(speed)
            cols["vib"].append(vib)
            cols["seg"].append(np.full(len(true), kind))
        cols["cycle"].append(np.full(n, c))
        walk = np.cumsum(rng.standard_normal(n)) * model.bias_walk_dps_rt_s / np.sqrt(fs)
        cols["on"].append(turn_on + walk)
        clock += n / fs + model.off_s
    cat = {k: np.concatenate(v) for k, v in cols.items()}
    temp = (model.cabin_end_c - (model.cabin_end_c - model.cabin_start_c)
            * np.exp(-cat["clock"] / model.cabin_tau_s))
    temp_read = np.round(temp + 0.05 * rng.standard_normal(temp.size), 2)
    reference = model.cabin_start_c if model.slope_reference_c is None else model.slope_reference_c
    bias = cat["on"] + model.temp_slope_dps_per_c * (temp - reference)
    rate = cat["true"] + bias + cat["vib"] + model.white_dps * rng.standard_normal(temp.size)
    return Drive(time_s=cat["time"], clock_s=cat["clock"], rate_dps=rate, true_rate_dps=cat["true"],
                 bias_dps=bias, temp_c=temp_read, speed_mps=cat["speed"], segment=cat["seg"],
                 cycle=cat["cycle"], rate_hz=fs)


@dataclass(frozen=True)
class DriveFigures:
    """What a tracker did on a simulated drive, against the truth the simulator knows.

    Heading error is the integral of the corrected rate's error (noise and vibration included)
    over the time switched on, to the end of the drive. Rate error while driving is the applied
    bias's error on moving rows: the part bias tracking is for (white noise and vibration are
    the same with or without it). A window's learning "moves" the bias by the change it made to
    the learned bias at its temperature; it counts for a segment when its samples overlap it.
    """

    heading_untracked_deg: float
    heading_tracked_deg: float
    rate_error_untracked_rms_dps: float
    rate_error_tracked_rms_dps: float
    moved_in_turn_dps: float
    moved_in_creep_dps: float
    windows_in_turn: int
    windows_in_creep: int

    @property
    def heading_ratio(self) -> float:
        return abs(self.heading_tracked_deg) / abs(self.heading_untracked_deg)


def drive_figures(drive: Drive, applied_dps: np.ndarray, taken: tuple[TakenWindow, ...] | list[TakenWindow],
                  ) -> DriveFigures:
    """Figures of one axis's applied bias (per row) and the windows it learned from."""
    applied = np.asarray(applied_dps, dtype=float).reshape(len(drive.time_s), -1)[:, 0]
    dt = 1.0 / drive.rate_hz
    error = drive.rate_dps - drive.true_rate_dps
    moving = drive.moving
    moved = {TURN: [0.0, 0], CREEP: [0.0, 0]}
    for w in taken:
        rows = (drive.cycle == w.power_cycle) & (drive.time_s >= w.start_s) & (drive.time_s <= w.end_s)
        for kind, tally in moved.items():
            if np.any(drive.segment[rows] == kind):
                tally[0] += max(abs(a - b) for a, b in zip(w.after_dps, w.before_dps, strict=True))
                tally[1] += 1
    return DriveFigures(
        heading_untracked_deg=float(np.sum(error) * dt),
        heading_tracked_deg=float(np.sum(error - applied) * dt),
        rate_error_untracked_rms_dps=float(np.sqrt(np.mean(drive.bias_dps[moving] ** 2))),
        rate_error_tracked_rms_dps=float(np.sqrt(np.mean((applied - drive.bias_dps)[moving] ** 2))),
        moved_in_turn_dps=float(moved[TURN][0]),
        moved_in_creep_dps=float(moved[CREEP][0]),
        windows_in_turn=int(moved[TURN][1]),
        windows_in_creep=int(moved[CREEP][1]),
    )
