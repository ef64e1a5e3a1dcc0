"""Plateaus left out at a rail: from the signal's definition, never from a recurring extreme value."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import cantools
import numpy as np
import pytest

from canical.calibrate.rails import RailLimits, rail_plateaus
from canical.calibration.pipeline import CalibrateOptions, find_plateaus, fit_base
from canical.sessions.canlog import signal_rail
from canical.sessions.csv_file import format_session
from canical.sessions.session import Rail, Session
from canical.sim.gyro import GyroModel
from canical.sim.sessions import paper_rates, sweep_session

SEEDS = (0, 1, 2)
#: A vendor's gyro: int16 at 0.1 deg/s (the physical value is the rate, quantised to 0.1 deg/s).
QUANTISED = GyroModel(sensitivity=1.0, bias_counts=0.3, lsb=0.1, rail_counts=3276.7)
VENDOR_RAIL = RailLimits(-3276.8, 3276.7, "DBC signal TPDO2.GyroZ", 0.1)
#: 16.4 LSB/(deg/s), an on-chip low-pass filter and little noise: the extreme value recurs.
FILTERED = GyroModel(sensitivity=16.4, bias_counts=5.0, full_scale_dps=250.0, noise_dps=0.03,
                     bandwidth_hz=5.0)
#: A sensor whose converter clips at 20000 counts (50 deg/s), turned to ±60 deg/s.
CLIPPING = GyroModel(rail_counts=20000.0)


def _left_out(session: Session, rail: RailLimits | None) -> np.ndarray:
    plateaus = find_plateaus(session, CalibrateOptions())
    return plateaus.rate_dps[rail_plateaus(session.raw, plateaus, rail).left_out]


@pytest.mark.parametrize("seed", SEEDS)
def test_a_quantised_sensor_keeps_every_plateau_inside_its_range(seed: int) -> None:
    session = sweep_session(QUANTISED, paper_rates(), dwell_s=4.0, seed=seed)
    assert _left_out(session, None).size == 0
    assert _left_out(session, VENDOR_RAIL).size == 0
    base = fit_base(session, CalibrateOptions(segments=3, order=2, extend=False))
    assert base.points.rate.min() == pytest.approx(-60.0) and base.points.rate.max() == pytest.approx(60.0)


@pytest.mark.parametrize("seed", SEEDS)
def test_a_low_pass_filtered_sensor_keeps_its_200_dps_plateau(seed: int) -> None:
    session = sweep_session(FILTERED, paper_rates(25.0, 200.0), dwell_s=4.0, seed=seed)
    assert _left_out(session, None).size == 0
    assert _left_out(session, RailLimits(-32768, 32767, "int16", 1.0)).size == 0


@pytest.mark.parametrize("declared", [False, True])
def test_a_sensor_at_its_rail_still_has_those_plateaus_left_out(declared: bool) -> None:
    session = sweep_session(CLIPPING, paper_rates(), dwell_s=4.0, seed=1)
    rail = RailLimits(-20001.0, 20000.0, "--rail", 0.0) if declared else None
    left = set(_left_out(session, rail).tolist())
    # Every plateau beyond the rail (|rate| > ~50 deg/s on this sensor's curve) is left out.
    assert {-60.0, -57.0, 51.0, 54.0, 57.0, 60.0} <= left
    assert all(abs(r) > 48 for r in left)


def test_plateaus_left_out_are_named_in_the_report() -> None:
    session = replace(sweep_session(CLIPPING, paper_rates(), dwell_s=4.0, seed=1),
                      rail=Rail(-20001.0, 20000.0, "--rail"))
    base = fit_base(session, CalibrateOptions(segments=3, order=2, extend=False))
    assert sorted(p.rate_dps for p in base.left_out) == [-60.0, -57.0, -54.0, 51.0, 54.0, 57.0, 60.0]
    first = base.left_out[0]
    assert "at the rail -20001 (--rail)" in first.label() and first.start_s < first.stop_s
    assert base.saturated_rates == (-60.0, -57.0, -54.0, 51.0, 54.0, 57.0, 60.0)


VENDOR_DBC = """VERSION ""
NS_ :
BS_:
BU_: IMU
BO_ 648 TPDO2: 6 IMU
 SG_ GyroX : 0|16@1- (0.1,0) [-3276.8|3276.7] "deg/s" Vector__XXX
 SG_ GyroY : 16|16@1- (0.1,0) [-250|250] "deg/s" Vector__XXX
 SG_ GyroZ : 32|16@1+ (0.01,-300) [0|0] "deg/s" Vector__XXX
"""


def test_a_dbc_signal_gives_its_rail_from_width_scale_offset_and_declared_range() -> None:
    msg = cantools.database.load_string(VENDOR_DBC, "dbc").get_message_by_name("TPDO2")
    x = signal_rail(msg.get_signal_by_name("GyroX"), "TPDO2.GyroX")
    assert (x.low, x.high, x.resolution) == pytest.approx((-3276.8, 3276.7, 0.1))
    assert "16-bit signed, scale 0.1" in x.source
    y = signal_rail(msg.get_signal_by_name("GyroY"), "TPDO2.GyroY")
    assert (y.low, y.high) == (-250.0, 250.0) and "declared -250 to 250" in y.source
    z = signal_rail(msg.get_signal_by_name("GyroZ"), "TPDO2.GyroZ")
    assert (z.low, z.high) == pytest.approx((-300.0, -300.0 + 0.01 * 65535))


def _calibrate(*args: str) -> int:
    from canical.commands.cli import main

    return main(["calibrate", *args])


def test_the_normal_output_names_each_plateau_left_out(tmp_path: Path, capsys) -> None:
    """A CSV declaring its rail: the plateaus at it are named on stdout and in report.json."""
    session = sweep_session(CLIPPING, paper_rates(), dwell_s=4.0, seed=1)
    path = tmp_path / "clipped.csv"
    path.write_text("# rail: -20001,20000\n" + format_session(session))
    assert _calibrate(str(path), "--no-extend", "--segments", "3", "--order", "2", "-o",
                      str(tmp_path / "set.yaml"), "--report", str(tmp_path / "r.json")) == 0
    out = capsys.readouterr().out
    named = [line for line in out.splitlines() if line.startswith("left out")]
    assert len(named) == 7 and "60 deg/s at" in named[-1] and "# rail" in named[-1]
    import json

    report = json.loads((tmp_path / "r.json").read_text())
    assert [p["rate_dps"] for p in report["left_out_plateaus"]] == [-60, -57, -54, 51, 54, 57, 60]


@pytest.mark.parametrize("header, option", [("# rail: 20000\n", ()), ("", ("--rail", "5,1"))])
def test_a_bad_rail_is_one_line_exit_2_nothing_written(tmp_path: Path, capsys, header: str,
                                                        option: tuple[str, ...]) -> None:
    session = sweep_session(CLIPPING, paper_rates(step=12.0), dwell_s=2.0, seed=1)
    path = tmp_path / "s.csv"
    path.write_text(header + format_session(session))
    out = tmp_path / "set.yaml"
    try:
        code = _calibrate(str(path), *option, "-o", str(out))
    except SystemExit as stop:  # argparse refuses the option's value
        code = int(stop.code or 0)
    assert code == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert "rail" in err[-1] and "LO,HI" in err[-1]
    assert not out.exists()
