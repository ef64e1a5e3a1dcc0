"""A three-axis IMU on a rate table, sample by sample: what the emulated device transmits.

The table turns about one axis (plateaus with ramps, a constant rate, or still);
each axis has its own simulated gyro (:class:`canical.sim.gyro.GyroModel`, with
whatever effects it is given), fed the table rate on the table's axis and zero
on the others. The environment the effects see, and that the device reports,
is a die temperature warming up after power-on (``temp_c``) and a supply
voltage (``supply_v``). Samples come in blocks, one pass of the table
programme each, times continuing from block to block; a step programme ends at
0 deg/s so consecutive passes join without a jump.
"""

from __future__ import annotations

import itertools
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field

import numpy as np

from canical.frames.imu_dictionary import AXES
from canical.sim.gyro import GyroModel
from canical.sim.paired_noise import plateau_paired_noise
from canical.sim.rate_table import constant_profile, step_profile
from canical.sim.sessions import paper_rates
from canical.sim.table_recording import TableBehaviour, record_table

TABLE_KINDS = ("steps", "constant", "still")


def default_gyros() -> dict[str, GyroModel]:
    """Three different parts, as a real IMU's axes are."""
    return {
        "x": GyroModel(sensitivity=395.0, bias_counts=-85.0, asymmetry=0.025, cubic=-0.03),
        "y": GyroModel(sensitivity=405.0, bias_counts=120.0, asymmetry=0.035, quadratic=0.01),
        "z": GyroModel(),
    }


@dataclass(frozen=True)
class TableMotion:
    """The rate table's programme."""

    kind: str = "steps"
    axis: str = "z"
    rates_dps: tuple[float, ...] = tuple(float(r) for r in paper_rates())
    dwell_s: float = 3.0
    accel_dps2: float = 100.0
    rate_dps: float = 0.0  # for kind "constant"
    block_s: float = 10.0  # block length of "constant" and "still"
    #: For kind "steps": move and record as a real table does (ramps, S-curves, ringing, a
    #: measured, held, late or asynchronous ``TABLE_REF``, IMU frames lost in bursts);
    #: ``accel_dps2`` above is then unused (the behaviour's own limits apply).
    recording: TableBehaviour | None = None


@dataclass(frozen=True)
class StreamConfig:
    """Everything that shapes the stream; the same config and seed give the same samples."""

    sample_rate_hz: float = 100.0
    table: TableMotion = field(default_factory=TableMotion)
    gyros: dict[str, GyroModel] = field(default_factory=default_gyros)
    temp_start_c: float = 24.0
    temp_rise_c: float = 12.0
    temp_tau_s: float = 90.0
    temp_noise_c: float = 0.03
    #: Instead of the warm-up: ``f(time_s, rate_dps, rng) -> temp_c`` (see :mod:`canical.sim.environment`).
    temperature: Callable[[np.ndarray, np.ndarray, np.random.Generator], np.ndarray] | None = None
    supply_v: float = 5.0
    supply_noise_v: float = 0.003
    seed: int = 0


@dataclass(frozen=True)
class Block:
    """Consecutive samples of all three axes."""

    time_s: np.ndarray
    table_rate_dps: np.ndarray
    settled: np.ndarray
    raw: dict[str, np.ndarray]
    temp_c: np.ndarray
    supply_v: np.ndarray
    #: With a recording table: the reference per sample, which samples' frames are sent, and
    #: the table's own frames (times, rates, settled flags) when they are not one per sample.
    ref_dps: np.ndarray | None = None
    kept: np.ndarray | None = None
    table_frames: tuple[np.ndarray, np.ndarray, np.ndarray] | None = None

    def __len__(self) -> int:
        return int(self.time_s.shape[0])


def table_pass(table: TableMotion, fs_hz: float, t0_s: float) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Times, table rate and settled flag of one pass of the programme."""
    if table.kind == "steps":
        rates = np.concatenate([np.asarray(table.rates_dps, dtype=float), [0.0]])
        t, w = step_profile(rates, dwell_s=table.dwell_s, fs_hz=fs_hz, accel_dps2=table.accel_dps2, t0_s=t0_s)
    else:
        n = max(1, round(table.block_s * fs_hz))
        rate = table.rate_dps if table.kind == "constant" else 0.0
        t, w = constant_profile(rate, n, fs_hz=fs_hz, t0_s=t0_s)
    settled = np.ones(w.shape, dtype=bool)
    settled[1:] = w[1:] == w[:-1]
    if len(w) > 1:
        settled[0] = w[0] == w[1]
    return t, w, settled


def imu_blocks(config: StreamConfig) -> Iterator[Block]:
    """Blocks of samples, forever (the table programme repeats)."""
    if config.table.kind not in TABLE_KINDS:
        raise ValueError(f"table kind {config.table.kind!r} (known: {', '.join(TABLE_KINDS)})")
    fs = config.sample_rate_hz
    rng = np.random.default_rng(config.seed)
    t0 = 0.0
    recording = config.table.recording if config.table.kind == "steps" else None
    # A recording table draws from its own generator and the gyros' noise is tied to the
    # instants of each plateau, so the same seed on two tables is the same sensor noise.
    table_rng = np.random.default_rng([config.seed, 1])
    for n_pass in itertools.count():
        extra: dict = {}
        noise: dict[str, np.ndarray | None] = dict.fromkeys(AXES)
        if recording is not None:
            rates = np.concatenate([np.asarray(config.table.rates_dps, dtype=float), [0.0]])
            rec = record_table(rates, dwell_s=config.table.dwell_s, fs_hz=fs, behaviour=recording,
                               rng=table_rng, t0_s=t0, initial_dps=0.0)
            noise = {a: plateau_paired_noise(config.gyros[a], rec.schedule, rec.time_s,
                                             dwell_s=config.table.dwell_s, fs_hz=fs,
                                             seed=(config.seed, n_pass, i))
                     for i, a in enumerate(AXES)}
            t, w, settled = rec.time_s, rec.true_dps, rec.settled
            frames = None if recording.ref_rate_hz is None else (rec.frame_time_s, rec.frame_dps,
                                                                    rec.frame_settled)
            extra = {"ref_dps": rec.ref_dps, "kept": rec.kept, "table_frames": frames}
        else:
            t, w, settled = table_pass(config.table, fs, t0)
        if config.temperature is not None:
            temp = np.asarray(config.temperature(t, w, rng), dtype=float)
        else:
            temp = (
                config.temp_start_c
                + config.temp_rise_c * (1.0 - np.exp(-t / config.temp_tau_s))
                + config.temp_noise_c * rng.standard_normal(t.size)
            )
        supply = config.supply_v + config.supply_noise_v * rng.standard_normal(t.size)
        aux = {"temp_c": temp, "supply_v": supply}
        raw = {}
        for axis in AXES:
            rate = w if axis == config.table.axis else np.zeros_like(w)
            raw[axis] = config.gyros[axis].output(t, rate, aux=aux, rng=rng, fs_hz=fs, noise_dps=noise[axis])
        yield Block(t, w, settled, raw, temp, supply, **extra)
        t0 = float(t[-1]) + 1.0 / fs
