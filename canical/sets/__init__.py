"""A coefficient set: what calibration writes and everything else reads.

:mod:`.coefficients` is the set as typed records (its rate model, :mod:`.set_model`, one record per
model kind, plus effect terms),
:mod:`.coefficient_file` its YAML file with CRC (and :mod:`.finite_outputs` the proof at load that
its outputs are finite), :mod:`.term_kinds` the registry of effect term kinds (one object per
kind), :mod:`.terms` the validated term record (a common core), :mod:`.term_params` each
kind's parameter record, :mod:`.trackers` the terms' state,
:mod:`.corrector` applies a set to samples (block and per-sample paths),
:mod:`.fast_corrector` compiles it into straight-line code for the daemon, and
:mod:`.admission` decides which sets a device may take; :mod:`.imu_set` is the IMU set (three axes and
their coupling, one CRC) and :mod:`.imu_corrector` applies it; :mod:`.signing` signs and
verifies a set's origin (Ed25519) and :mod:`.signed_file` reads and signs set files with their
signatures. Imports only :mod:`canical.models` and the ground floor.
"""

# The package's public face: the submodules other rings and the tests import;
# tests/test_rings.py keeps this list equal to those imports.
__all__ = ["admission", "coefficient_file", "coefficients", "corrector", "fast_corrector",
           "finite_outputs", "imu_corrector", "imu_set", "set_model", "signed_file", "signing",
           "term_kinds", "term_params", "terms", "trackers"]
