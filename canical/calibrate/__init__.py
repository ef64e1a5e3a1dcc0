"""From a session's samples to a fitted rate model: the paper's calibration steps.

Plateaus of constant table rate (:mod:`.plateaus`), the zero-rate bias V0 (:mod:`.zero_bias`),
one fit point per plateau (:mod:`.fit_points`), segment points at extrema of a global fit's
residual (:mod:`.segment_points`), the models fitted (:mod:`.model_fit`) and their size chosen
by cross-validation (:mod:`.cross_validation`, :mod:`.model_selection`); the sensor's noise by
its Allan deviation (:mod:`.allan`, :mod:`.noise_records`).

Pure functions on numpy arrays and plain data; imports only :mod:`canical.models` and the
ground floor.
"""
