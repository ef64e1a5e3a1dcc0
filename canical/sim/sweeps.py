"""A turntable session recorded as a slow continuous sweep, with an encoder's rate as reference.

The table sweeps a triangle between ±limit at a constant angular acceleration (its programme is
the rate table's own: ramps between ±limit with no dwell, :func:`~canical.sim.table_recording.
record_table`), starting and ending at rest. Its reference is the *measured* rate, quantised to
the encoder's step, sent at ``ref_hz`` and held between updates, optionally late; the sensor is
sampled at ``fs_hz``.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from canical.sessions.session import Session
from canical.sim.gyro import GyroModel
from canical.sim.table_recording import TableBehaviour, record_table


@dataclass(frozen=True)
class SweepProgramme:
    """A triangle sweep and how its rate is recorded."""

    duration_s: float = 420.0  # the whole session, from rest to rest
    limit_dps: float = 60.0
    cycles: int = 1  # full triangles: 0 → +limit → −limit → 0 is one
    ref_hz: float = 100.0
    encoder_lsb_dps: float = 0.01
    jitter_dps: float = 0.0
    ref_latency_s: float = 0.0
    fs_hz: float = 200.0

    @property
    def sweep_dps2(self) -> float:
        """The acceleration that covers the programme in ``duration_s``: 4·limit per cycle."""
        return 4.0 * self.limit_dps * self.cycles / self.duration_s

    def rates(self) -> np.ndarray:
        """The turning points: +limit, −limit, … and back to rest."""
        turns = [self.limit_dps if k % 2 == 0 else -self.limit_dps for k in range(2 * self.cycles)]
        return np.array([*turns, 0.0])

    def behaviour(self) -> TableBehaviour:
        return TableBehaviour(accel_dps2=self.sweep_dps2, reference="measured",
                              encoder_lsb_dps=self.encoder_lsb_dps, jitter_dps=self.jitter_dps,
                              ref_rate_hz=self.ref_hz, ref_latency_s=self.ref_latency_s)


def sweep_recording(gyro: GyroModel, programme: SweepProgramme, *, seed: int = 0, sensor: str = "SIM-0001",
                    axis: str = "z") -> Session:
    """The sensor through ``programme``: its noise from ``seed``, the table's from ``seed + 1``."""
    rec = record_table(programme.rates(), dwell_s=0.0, fs_hz=programme.fs_hz, behaviour=programme.behaviour(),
                       rng=np.random.default_rng(seed + 1), initial_dps=0.0)
    raw = gyro.output(rec.time_s, rec.true_dps, rng=np.random.default_rng(seed), fs_hz=programme.fs_hz)
    return Session(rec.time_s, raw, rec.ref_dps, {}, {"sensor": sensor, "axis": axis})
