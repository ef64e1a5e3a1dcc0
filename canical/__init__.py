"""canical: scale-factor calibration of MEMS gyroscopes on the CAN bus.

The science (Tang et al., "An improved scale factor calibration model of MEMS
gyroscopes") lives in pure modules — :mod:`canical.plateaus`, :mod:`canical.models`,
:mod:`canical.segment_points`, :mod:`canical.model_selection` — that take and return
numpy arrays and plain data. File, CAN, CANopen and CLI layers sit around them.
"""

__version__ = "0.1.0"
