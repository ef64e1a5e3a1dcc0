"""A coefficient set: what calibration writes and everything else reads.

:mod:`.coefficients` is the set as plain data (rate model pieces plus effect terms),
:mod:`.coefficient_file` its YAML file with CRC, :mod:`.terms` the effect term kinds,
:mod:`.corrector` applies a set to samples (block and per-sample paths),
:mod:`.fast_corrector` compiles it into straight-line code for the daemon, and
:mod:`.admission` decides which sets a device may take. Imports only :mod:`canical.models`
and the ground floor.
"""
