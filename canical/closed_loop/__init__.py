"""Closing the loop: find what the rate model lacks, and say what stays unexplained.

:mod:`.blocks` cuts a session into held-out blocks, :mod:`.candidates` builds candidate
variables from the session's channels (levels, derivatives, lags, hysteresis, rate-gated),
:mod:`.search` adds effects that win on held-out data and reports confounds (:mod:`.drift_steps`
finds where the sensor's bias jumped, so that a channel is judged against the session's drift
without the jumps), and :mod:`.unexplained` compares what remains with the session's noise floor.
Imports
:mod:`canical.calibrate`, :mod:`canical.sets`, :mod:`canical.sessions`, :mod:`canical.models`.
"""

# The package's public face: the submodules (and names) other rings and the tests import;
# tests/test_rings.py keeps this list equal to those imports.
__all__ = [
    "blocks",
    "candidates",
    "drift_steps",
    "findings",
    "search",
    "unexplained",
]
