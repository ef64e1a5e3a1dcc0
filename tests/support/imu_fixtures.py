"""Shared by the IMU (CANopen) tests and benchmarks: coefficient sets for the emulated device.

Sets are calibrated from simulated turntable sessions of the emulated IMU's own axes
(:func:`canical.sim.imu_stream.default_gyros`), with fixed model sizes and no effect
search so they are quick to make; two families (seeds) give two distinct sets per axis.
"""

from __future__ import annotations

import dataclasses
import functools

from canical.calibration.imu_pipeline import calibrate_imu
from canical.calibration.pipeline import CalibrateOptions, calibrate
from canical.frames.imu_dictionary import AXES
from canical.sets.coefficients import CoefficientSet
from canical.sets.imu_set import ImuSet
from canical.sim.imu_stream import default_gyros
from canical.sim.sessions import paper_session
from canical.sim.triad import axis_session, random_triad

SERIAL = 4711
# Sets carry the time they were made, and their CRC with it: a fixed time keeps a fixture's CRC (and
# the 4-bit set tag the bus carries) the same from one run to the next.
CREATED = "2026-01-01T00:00:00Z"
SENSOR = str(SERIAL)
FAST = CalibrateOptions(segments=3, order=3, extend=False)


def imu_set(axis: str, family: int = 0, sensor: str = SENSOR) -> CoefficientSet:
    """A valid set for one axis of the emulated IMU (``family`` picks the noise seed); the same
    arguments give the very same set (and CRC) on every run."""
    return _imu_set(axis, family, sensor)


@functools.cache
def _imu_set(axis: str, family: int, sensor: str) -> CoefficientSet:
    session = paper_session(default_gyros()[axis], seed=10 * family + AXES.index(axis), dwell_s=3.0,
                            sensor=sensor, axis=axis)
    made = calibrate(session, FAST, sensor_id=sensor, axis=axis).coefficients
    return dataclasses.replace(made, created=CREATED)


def imu_sets(family: int = 0, sensor: str = SENSOR) -> dict[str, CoefficientSet]:
    return {a: imu_set(a, family, sensor) for a in AXES}


def imu_triad_set(seed: int = 0, sensor: str = SENSOR) -> ImuSet:
    """A realistic IMU set for the emulated IMU: a simulated triad (:mod:`canical.sim.triad`, its
    coupling 0.4–2 %) calibrated from one short session per table axis; the same arguments give
    the very same set (and CRC) on every run."""
    return _imu_triad_set(seed, sensor)


@functools.cache
def _imu_triad_set(seed: int, sensor: str) -> ImuSet:
    triad = random_triad(seed)
    sessions = [axis_session(triad, axis, dwell_s=1.5, seed=100 * seed + k, sensor=sensor)
                for k, axis in enumerate(AXES)]
    return dataclasses.replace(calibrate_imu(sessions, FAST, sensor_id=sensor).imu_set, created=CREATED)
