"""Calibration with the scale paths gives the in-memory, per-sample path's set and report.

The session is read block by block (``read_session`` through ``csv_chunks.read_columns``), the
closed loop's blocks take the direction a flip at a time (``direction_steps``, the same bits)
and the slope filtered at once (``slope_filter``, equal within rounding). Here the same session
is calibrated both ways, the old way being ``read_table`` and the per-sample trackers.
"""

from __future__ import annotations

import numpy as np
import pytest

from canical.calibration.pipeline import CalibrateOptions, calibrate
from canical.closed_loop import blocks
from canical.sessions.csv_file import format_session, read_session, read_table, session_from_table
from canical.sets.trackers import direction_state, slope_state
from canical.sim.gyro import GyroModel
from canical.sim.sessions import paper_rates, sweep_session


def flat(value, prefix=""):
    """Every number in a nested report, by its path."""
    if isinstance(value, dict):
        return {k: v for key, item in value.items() for k, v in flat(item, f"{prefix}/{key}").items()}
    if isinstance(value, list | tuple):
        return {k: v for i, item in enumerate(value) for k, v in flat(item, f"{prefix}/{i}").items()}
    return {prefix: value}


def test_same_set_and_report_as_the_in_memory_path(tmp_path, monkeypatch):
    rates = np.concatenate([paper_rates(), paper_rates()[::-1]])
    session = sweep_session(GyroModel(), rates, dwell_s=2.3, fs_hz=1000.0, seed=5)
    assert 190_000 < len(session) < 210_000
    path = tmp_path / "s.csv"
    path.write_text(format_session(session))

    def run(s):
        return calibrate(s, CalibrateOptions(), sensor_id="S", axis="z")

    new = run(read_session(path))
    with monkeypatch.context() as m:
        m.setattr(blocks, "direction_steps", direction_state)
        m.setattr(blocks, "slope_filter", slope_state)
        old = run(session_from_table(read_table(path)))
    assert new.coefficients.terms == old.coefficients.terms
    a, b = flat(new.coefficients.model.to_dict()), flat(old.coefficients.model.to_dict())
    assert a.keys() == b.keys()
    for key in a:
        if isinstance(a[key], float):
            assert a[key] == pytest.approx(b[key], rel=1e-9, abs=1e-12), key
        else:
            assert a[key] == b[key], key
    ra, rb = flat(new.report.to_dict()), flat(old.report.to_dict())
    assert ra.keys() == rb.keys()
    for key in ra:
        if isinstance(ra[key], float):
            assert ra[key] == pytest.approx(rb[key], rel=1e-6, abs=1e-12, nan_ok=True), key
        else:
            assert ra[key] == rb[key], key
