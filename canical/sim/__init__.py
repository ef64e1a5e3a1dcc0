"""A virtual rate table and MEMS gyro, producing sessions in canical's CSV format.

Imports only :mod:`canical.sets` (effects are written as terms), :mod:`canical.sessions` and
the ground floor; the grid trials that run calibration on it are :mod:`support.trials`.

* :mod:`canical.sim.rate_table` — table motion: plateaus with finite acceleration between them;
* :mod:`canical.sim.table_recording` — the table as real equipment records it: acceleration- and
  jerk-limited rate changes, servo ringing, a commanded or measured reference, held, late or
  asynchronous, rows lost in bursts (``sweep_session(..., table=TableBehaviour(...))``);
* :mod:`canical.sim.table_file` — a table that logs its rate to its own file, on its own clock;
* :mod:`canical.sim.gyro` — the sensor: scale factor, smooth asymmetric nonlinearity, bias,
  bandwidth, white noise, quantisation, saturation, and pluggable *effects* the calibrator is
  not told about (:class:`canical.sim.gyro.Effect`);
* :mod:`canical.sim.sessions` — ready-made sessions: the paper's protocol, its validation records;
* :mod:`canical.sim.sweeps` — a session recorded as a slow continuous triangle sweep, its reference
  an encoder's rate (quantised, held at 100 Hz);
* :mod:`canical.sim.blind` — blind cases for the closed loop: effect forms, channel trajectories and
  drifts drawn at random from a seed, with what a right answer is;
* :mod:`canical.sim.compression` — sensors whose output compresses near its rail, drawn at random,
  and a model's error against their truth;
* :mod:`canical.sim.triad` — a gyro triad with coupling between its axes, single- and multi-axis tables;
* :mod:`canical.sim.fleet` — a fleet's field logs drawn from sensor lots, climates and planted aging
  and failing sensors, with the truth (imports :mod:`canical.fieldlog` too).
"""

# The package's public face: the submodules (and names) other rings and the tests import;
# tests/test_rings.py keeps this list equal to those imports.
__all__ = [
    "blind",
    "bus_log",
    "compression",
    "drive",
    "effects",
    "environment",
    "fleet",
    "fleet_drives",
    "gyro",
    "imu_stream",
    "rate_table",
    "scenarios",
    "sessions",
    "sweeps",
    "table_file",
    "table_recording",
    "triad",
]
