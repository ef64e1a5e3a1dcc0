"""The calibration API: a session in, a checked coefficient set and its report out.

:mod:`pipeline` calibrates one axis (plateaus, rate model, closed loop), :mod:`imu_pipeline`
a triad with its coupling, :mod:`evaluation` judges a set on held-out data;
:mod:`calibration_report` and :mod:`imu_calibration_report` are the records they write for the
report, :mod:`set_fit` the ``fit`` section a set carries.
"""

# The package's public face (tests/test_rings.py keeps it equal to what other rings import).
__all__ = ["calibration_report", "evaluation", "imu_calibration_report", "imu_pipeline", "pipeline"]
