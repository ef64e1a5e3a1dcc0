"""Triad session CSVs: the three raw columns and the table axis read back as written; bad ones refused."""

import numpy as np
import pytest

from canical.errors import CanicalError
from canical.sessions.triad_session import (
    check_axes_covered,
    format_triad_session,
    parse_table_axis,
    read_triad_session,
)
from canical.sim.triad import axis_session, multi_axis_rates, multi_axis_session, random_triad


@pytest.mark.parametrize("axis", ["x", "-y", "z"])
def test_a_single_axis_session_round_trips(axis, tmp_path):
    session = axis_session(random_triad(1), axis, rates_dps=np.array([0.0, 20.0, -20.0, 0.0]), dwell_s=0.5)
    path = tmp_path / "s.csv"
    path.write_text(format_triad_session(session))
    back = read_triad_session(path)
    assert back.table_axis == session.table_axis
    np.testing.assert_allclose(back.raw, session.raw)
    np.testing.assert_allclose(back.rate_dps, session.rate_dps, atol=1e-7)
    turning = np.abs(back.rate_dps).max(axis=0) > 0
    assert turning.tolist() == [axis.endswith(a) for a in "xyz"]


def test_a_multi_axis_session_round_trips(tmp_path):
    session = multi_axis_session(random_triad(1), multi_axis_rates(3), dwell_s=0.5)
    path = tmp_path / "m.csv"
    path.write_text(format_triad_session(session))
    back = read_triad_session(path)
    assert back.table_axis is None
    np.testing.assert_allclose(back.rate_dps, session.rate_dps, atol=1e-6)
    assert (np.abs(back.rate_dps).max(axis=0) > 0).all()


def test_the_upside_down_axis_turns_the_imu_axis_the_other_way():
    axis = parse_table_axis("-y", "t")
    assert axis is not None and (axis.index, axis.sign, axis.label) == (1, -1.0, "-y")
    assert parse_table_axis("multi", "t") is None


@pytest.mark.parametrize(("text", "message"), [
    ("time_s,ref_dps,raw_x,raw_y,raw_z\n0,0,1,2,3\n", "no '# axis:' line"),
    ("# axis: w\ntime_s,ref_dps,raw_x,raw_y,raw_z\n0,0,1,2,3\n", "'# axis: w' is not an IMU axis"),
    ("# axis: x\ntime_s,ref_dps,raw_x,raw_y\n0,0,1,2\n", "missing column 'raw_z'"),
    ("# axis: multi\ntime_s,ref_dps,raw_x,raw_y,raw_z\n0,0,1,2,3\n", "missing column 'ref_x_dps'"),
])
def test_bad_sessions_are_one_line(text, message, tmp_path):
    path = tmp_path / "bad.csv"
    path.write_text(text)
    with pytest.raises(CanicalError, match=message):
        read_triad_session(path)


def test_coverage_needs_one_session_per_axis():
    triad = random_triad(0)
    rates = np.array([0.0, 10.0, 0.0])
    x, y, z, minus_x = (axis_session(triad, a, rates_dps=rates, dwell_s=0.2) for a in ("x", "y", "z", "-x"))
    check_axes_covered([x, y, z])
    with pytest.raises(CanicalError, match="no session for z"):
        check_axes_covered([x, y])
    with pytest.raises(CanicalError, match="both turn about IMU axis x"):
        check_axes_covered([x, y, z, minus_x])
