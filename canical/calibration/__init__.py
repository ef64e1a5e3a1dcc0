"""The calibration API: a session in, a checked coefficient set and its report out.

:mod:`pipeline` calibrates one axis (plateaus, rate model, closed loop), :mod:`imu_pipeline`
a triad with its coupling, :mod:`evaluation` judges a set on held-out data, and
:mod:`calibration_report` is the record both write for the report.
"""

# The package's public face (tests/test_rings.py keeps it equal to what other rings import).
__all__ = ["calibration_report", "evaluation", "imu_pipeline", "pipeline"]
