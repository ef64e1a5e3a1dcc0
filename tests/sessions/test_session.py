"""A session's table rate: steps that need it get it or one actionable error."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given
from hypothesis import strategies as st
from hypothesis.extra.numpy import arrays

from canical.calibration.pipeline import CalibrateOptions, calibrate
from canical.errors import CanicalError
from canical.sessions.session import Session
from canical.sim.gyro import GyroModel
from canical.sim.sessions import paper_rates, sweep_session


@given(arrays(np.float64, st.integers(1, 50), elements=st.floats(-500, 500)))
def test_reference_is_the_recorded_table_rate(ref: np.ndarray) -> None:
    n = ref.size
    session = Session(np.arange(n, dtype=float), np.zeros(n), ref)
    assert session.reference() is ref
    mask = ref > 0
    assert np.array_equal(session.take(mask).reference(), ref[mask])


def test_field_session_without_reference_names_the_step() -> None:
    field = Session(np.arange(5, dtype=float), np.zeros(5))
    with pytest.raises(CanicalError, match="no reference rate column: cannot validate"):
        field.reference("validate")


def test_calibrating_a_field_session_fails_before_any_work() -> None:
    recorded = sweep_session(GyroModel(), paper_rates(step=60.0), dwell_s=2.0, seed=1)
    field = Session(recorded.time_s, recorded.raw)
    with pytest.raises(CanicalError, match="no reference rate column: cannot calibrate"):
        calibrate(field, CalibrateOptions(), sensor_id="SIM", axis="z")
