"""canical: scale-factor calibration of MEMS gyroscopes on the CAN bus.

The package is built in rings; each imports only rings below it (``tests/test_rings.py``
checks it on the import graph):

* ``commands/`` (one module per CLI verb, ``cli``) and ``trials/`` at the top;
* ``bus/`` (the daemon) over ``device/`` (the IMU as a CANopen node, and its emulation);
* ``pipeline`` and ``evaluation`` (a session to a coefficient set, judged on held-out data),
  beside ``report/``;
* ``closed_loop/`` (what the rate model lacks) beside ``sim/`` (the virtual table and gyro);
* ``sets/`` (the coefficient set and its evaluation);
* ``calibrate/`` (the paper's steps, pure functions) beside ``sessions/`` (data and files);
* ``models/`` (the three rate models) beside ``frames/`` (the DBC's frames and codecs);
* the ground floor: ``errors``, ``progress``, ``yaml_text``, ``output_plan``, ``atomic_file``,
  ``imu_dictionary``.

The science (Tang et al., "An improved scale factor calibration model of MEMS gyroscopes")
is the pure part: numpy arrays and plain data in and out, no I/O.
"""

__version__ = "0.1.0"
