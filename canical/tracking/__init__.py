"""The gyro bias learned on the vehicle at every standstill, and carried between stops.

A table calibration fixes the bias the sensor had on the table; on the vehicle the bias
changes at every power-on and drifts as the cabin warms. This package decides from the gyro
itself (and an optional cue such as vehicle speed) when the vehicle stands still
(:mod:`.standstill`), estimates each axis's bias there with its uncertainty and learns it
across standstills as a function of temperature (:mod:`.estimate`), and applies it with a
bounded slew (:mod:`.tracker`, one sample per call, the same code the daemon and the
offline replay run). Settings are :mod:`.config`, named records of what was adopted or
refused are :mod:`.events`. Pure Python and numpy on plain data; imports only the ground floor.
"""

# The package's public face: the submodules other rings and the tests import;
# tests/test_rings.py keeps this list equal to those imports.
__all__ = [
    "config",
    "estimate",
    "events",
    "explain",
    "fast_step",
    "replay",
    "settings",
    "state_file",
    "tracker",
]
