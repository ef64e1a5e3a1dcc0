"""From a session's samples to a fitted rate model: the paper's calibration steps.

Plateaus of constant table rate (:mod:`.plateaus`), or a continuous sweep's short windows
in their place (:mod:`.sweep_windows`), the zero-rate bias V0 (:mod:`.zero_bias`),
one fit point per plateau (:mod:`.fit_points`), segment points at extrema of a global fit's
residual (:mod:`.segment_points`), plateaus at a rail of the output left out
(:mod:`.rails`), the models fitted (:mod:`.model_fit`) and their size chosen
by cross-validation (:mod:`.cross_validation`, :mod:`.model_selection`); the sensor's noise by
its Allan deviation (:mod:`.allan`, :mod:`.noise_records`).

Pure functions on numpy arrays and plain data; imports only :mod:`canical.models` and the
ground floor. :mod:`.coupling` fits the coupling between a triad's axes from plateau means.
"""

# The package's public face: the submodules (and names) other rings and the tests import;
# tests/test_rings.py keeps this list equal to those imports.
__all__ = [
    "allan",
    "coupling",
    "cross_validation",
    "fit_points",
    "model_fit",
    "model_selection",
    "noise_records",
    "plateaus",
    "rails",
    "segment_points",
    "sweep_windows",
    "zero_bias",
]
