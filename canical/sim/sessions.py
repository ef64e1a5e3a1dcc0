"""Ready-made simulated sessions, as :class:`canical.sessions.session.Session` objects."""

from __future__ import annotations

from collections.abc import Callable

import numpy as np

from canical.sessions.session import Session
from canical.sim.gyro import GyroModel
from canical.sim.paired_noise import plateau_paired_noise
from canical.sim.rate_table import constant_profile, step_profile
from canical.sim.table_recording import TableBehaviour, TableRecording, record_table

# An auxiliary channel's generator: (time s, table rate deg/s, sensor rng) -> one value per sample.
AuxSignal = Callable[[np.ndarray, np.ndarray, np.random.Generator], np.ndarray]


def paper_rates(step: float = 3.0, limit: float = 60.0) -> np.ndarray:
    """−limit…limit in ``step`` increments: the paper's calibration protocol."""
    n = round(2 * limit / step)
    return np.linspace(-limit, limit, n + 1)


def sweep_session(
    gyro: GyroModel,
    rates_dps: np.ndarray,
    *,
    dwell_s: float = 10.0,
    fs_hz: float = 200.0,
    seed: int = 0,
    sensor: str = "SIM-0001",
    axis: str = "z",
    aux: dict[str, AuxSignal] | None = None,
    table: TableBehaviour | None = None,
) -> Session:
    """A turntable session visiting ``rates_dps`` in order.

    ``aux`` maps channel names to callables ``f(time_s, rate_dps, rng) -> values``
    (environment signals such as a temperature); they feed the gyro's effects and
    are recorded as auxiliary columns. ``table`` records the session as a real table
    would (ramps, ringing, a measured, held or late reference, lost rows: see
    :mod:`canical.sim.table_recording`); without it, the table ramps at 100 deg/s² from
    0 deg/s and the reference is the commanded rate at every sample.
    """
    if table is not None:
        return recorded_sweep(gyro, rates_dps, table, dwell_s=dwell_s, fs_hz=fs_hz, seed=seed,
                              sensor=sensor, axis=axis, aux=aux)[0]
    rng = np.random.default_rng(seed)
    t, w = step_profile(rates_dps, dwell_s=dwell_s, fs_hz=fs_hz)
    channels = {name: np.asarray(f(t, w, rng), dtype=float) for name, f in (aux or {}).items()}
    raw = gyro.output(t, w, aux=channels, rng=rng, fs_hz=fs_hz)
    return Session(t, raw, w, channels, {"sensor": sensor, "axis": axis})


def recorded_sweep(
    gyro: GyroModel,
    rates_dps: np.ndarray,
    table: TableBehaviour,
    *,
    dwell_s: float = 10.0,
    fs_hz: float = 200.0,
    seed: int = 0,
    sensor: str = "SIM-0001",
    axis: str = "z",
    aux: dict[str, AuxSignal] | None = None,
) -> tuple[Session, TableRecording]:
    """A session recorded through ``table``, and the table's truth for the kept rows' ticks.

    The sensor's noise is tied to the instants of each plateau (:mod:`canical.sim.paired_noise`),
    the table's comes from its own generator (``seed + 1``): the same sensor recorded on
    different tables sees the same noise at the same instant of every plateau.
    """
    sensor_rng = np.random.default_rng(seed)
    rec = record_table(rates_dps, dwell_s=dwell_s, fs_hz=fs_hz, behaviour=table,
                       rng=np.random.default_rng(seed + 1))
    t, w = rec.time_s, rec.true_dps
    channels = {name: np.asarray(f(t, w, sensor_rng), dtype=float) for name, f in (aux or {}).items()}
    noise = plateau_paired_noise(gyro, rec.schedule, t, dwell_s=dwell_s, fs_hz=fs_hz, seed=seed)
    raw = gyro.output(t, w, aux=channels, rng=sensor_rng, fs_hz=fs_hz, noise_dps=noise)
    keep = rec.kept
    session = Session(
        t[keep], raw[keep], rec.ref_dps[keep], {k: v[keep] for k, v in channels.items()},
        {"sensor": sensor, "axis": axis}, settled=rec.settled[keep] if table.settled_flag else None,
    )
    return session, rec


def paper_session(gyro: GyroModel | None = None, *, seed: int = 0, sweeps: int = 1, **kw) -> Session:
    """The paper's protocol: −60…60 deg/s in 3 deg/s steps, zero plateaus included."""
    rates = np.concatenate([paper_rates() if i % 2 == 0 else paper_rates()[::-1] for i in range(sweeps)])
    return sweep_session(gyro or GyroModel(), rates, seed=seed, **kw)


def between_rates_session(gyro: GyroModel | None = None, *, seed: int = 1, **kw) -> Session:
    """Held-out plateaus midway between the protocol's rates (−58.5…58.5), plus zero."""
    rates = paper_rates()[:-1] + 1.5
    rates = np.sort(np.concatenate([rates, [0.0]]))
    return sweep_session(gyro or GyroModel(), rates, seed=seed, **kw)


def constant_session(
    gyro: GyroModel | None,
    rate_dps: float,
    n: int = 50_000,
    *,
    fs_hz: float = 200.0,
    seed: int = 2,
    sensor: str = "SIM-0001",
    axis: str = "z",
) -> Session:
    """A long constant-rate record (the paper's validation at ±25 deg/s, 50,000 samples)."""
    gyro = gyro or GyroModel()
    rng = np.random.default_rng(seed)
    t, w = constant_profile(rate_dps, n, fs_hz=fs_hz)
    raw = gyro.output(t, w, rng=rng, fs_hz=fs_hz)
    return Session(t, raw, w, {}, {"sensor": sensor, "axis": axis})
