"""``calibrate`` from a vendor's CAN log plus the table controller's own file on its own clock."""

from __future__ import annotations

import json
import struct
from dataclasses import replace
from pathlib import Path

import can
import numpy as np
import pytest
import yaml
from support.table_clock import own_clock_case, table_csv

from canical.commands.cli import main
from canical.sessions.csv_file import format_session, read_table
from canical.sessions.reference_clock import align_reference, join_reference
from canical.sim.gyro import GyroModel

T0 = 1_700_000_000.0  # the logger's clock
#: A vendor's CANopen IMU: gyro in TPDO2 at 0x288, three int16 at 0.1 deg/s, no counter.
VENDOR_DBC = """VERSION ""
NS_ :
BS_:
BU_: IMU
BO_ 648 TPDO2: 6 IMU
 SG_ GyroX : 0|16@1- (0.1,0) [-3276.8|3276.7] "deg/s" Vector__XXX
 SG_ GyroY : 16|16@1- (0.1,0) [-3276.8|3276.7] "deg/s" Vector__XXX
 SG_ GyroZ : 32|16@1- (0.1,0) [-3276.8|3276.7] "deg/s" Vector__XXX
"""
#: Its output is the rate in deg/s, quantised to 0.1 deg/s.
QUANTISED = GyroModel(sensitivity=1.0, bias_counts=0.3, lsb=0.1, rail_counts=3276.7)


@pytest.fixture(scope="module")
def vendor_files(tmp_path_factory: pytest.TempPathFactory):
    folder = tmp_path_factory.mktemp("vendor")
    case = own_clock_case(0, gyro=QUANTISED, fs_hz=100.0, offset_s=5000.25, drift_ppm=-75.0)
    (folder / "vendor.dbc").write_text(VENDOR_DBC)
    with can.Logger(str(folder / "imu.log")) as log:
        for t, raw in zip(case.session.time_s, case.session.raw, strict=True):
            data = struct.pack("<hhh", 3, -2, round(float(raw) * 10))
            log.on_message_received(can.Message(timestamp=T0 + float(t), arbitration_id=0x288,
                                                is_extended_id=False, data=data))
    (folder / "table.csv").write_text(table_csv(case.table))
    return case, folder


def _run(folder: Path, *args: str) -> int:
    try:
        return main(["calibrate", *args])
    except SystemExit as stop:
        return int(stop.code or 0)


def test_a_vendor_log_calibrates_against_the_tables_own_file(vendor_files, capsys) -> None:
    case, folder = vendor_files
    code = _run(folder, str(folder / "imu.log"), "--dbc", str(folder / "vendor.dbc"),
                "--input", "raw=TPDO2.GyroZ", "--reference", str(folder / "table.csv"), "--no-extend",
                "-o", str(folder / "aligned.yaml"), "--report", str(folder / "aligned.json"))
    assert code == 0, capsys.readouterr().err
    out = capsys.readouterr().out
    assert out.splitlines()[0].startswith("reference  ") and "drift" in out
    report = json.loads((folder / "aligned.json").read_text())
    clock = report["reference_clock"]
    assert clock["offset_s"] == pytest.approx(5000.25, abs=0.1)
    assert clock["rate_changes_matched"] >= 38
    # The DBC's rail (±3276.8 deg/s) is nowhere near: every plateau to ±60 deg/s is kept.
    assert report["left_out_plateaus"] == [] and report["saturated_rates_dps"] == []
    assert report["rates"] == 41
    # "raw" is the DBC's physical value, and the set says in which unit.
    assert yaml.safe_load((folder / "aligned.yaml").read_text())["units"]["raw"] == "deg/s"

    # The same samples with the table's rate perfectly aligned, as a session CSV.
    fit = align_reference(case.session.time_s, case.session.raw, case.table)
    inside = join_reference(case.session.time_s, case.table, fit).inside
    perfect = join_reference(case.session.time_s, case.table, case.truth)
    session = replace(case.session, raw=np.round(case.session.raw * 10) / 10,
                      ref_dps=perfect.ref_dps).take(inside & perfect.inside)
    (folder / "perfect.csv").write_text(format_session(session))
    assert _run(folder, str(folder / "perfect.csv"), "--no-extend", "-o", str(folder / "perfect.yaml"),
                "--report", str(folder / "perfect.json")) == 0
    best = json.loads((folder / "perfect.json").read_text())["held_out"]["rms_dps"]
    assert report["held_out"]["rms_dps"] <= 1.5 * best


def test_a_session_csv_takes_the_tables_file_too(vendor_files, tmp_path: Path, capsys) -> None:
    case, folder = vendor_files
    path = tmp_path / "log.csv"
    path.write_text(format_session(case.session))  # no ref_dps column
    assert _run(tmp_path, str(path), "--reference", str(folder / "table.csv"), "--no-extend",
                "--segments", "3", "--order", "2", "-o", str(tmp_path / "set.yaml")) == 0
    assert "on its own clock: offset 5000.2" in capsys.readouterr().out


@pytest.mark.parametrize("what, table, extra, message", [
    ("flat", "time_s,ref_dps\n" + "".join(f"{i / 10},0\n" for i in range(100)), (), "never changes"),
    ("no column", "time_s,rate\n1,0\n2,0\n3,0\n4,0\n", (), "missing column 'ref_dps'"),
    ("backwards", "time_s,ref_dps\n1,0\n3,0\n2,0\n4,0\n5,0\n", (), "time goes backwards"),
    ("bad signal", None, ("--input", "raw=TPDO2.GyroW"), "has no signal GyroW"),
    # everything loaded is bounded before it is used (a span of 1e9 s asked for 149 GiB)
    ("clock spans 1e9 s", "time_s,ref_dps\n" + "".join(f"{i * 2e7:.0f},{i % 2}\n" for i in range(50)), (),
     "spans 9.8e+08 s, more than 7 days"),
    ("rate 1e300", "time_s,ref_dps\n" + "".join(f"{i},{1e300 if i == 7 else 0}\n" for i in range(50)), (),
     "row 8: rate 1e+300 deg/s is beyond ±100000 deg/s"),
    ("nan time", "time_s,ref_dps\n0,0\n1,0\nnan,0\n3,1\n4,1\n", (),
     "line 4, column time_s: value is not finite"),
    ("a CSV named .trc", "time_s,ref_dps\n0,0\n1,0\n2,1\n3,1\n", (),
     "not a CAN log in its suffix's format: 5 line(s) python-can could not read as .trc"),
])
def test_bad_inputs_are_one_line_exit_2_nothing_written(vendor_files, tmp_path: Path, capsys, what: str,
                                                        table: str | None, extra: tuple[str, ...],
                                                        message: str) -> None:
    _, folder = vendor_files
    reference = folder / "table.csv"
    if table is not None:
        reference = tmp_path / ("table.trc" if what.endswith(".trc") else "table.csv")
        reference.write_text(table)
    out = tmp_path / "set.yaml"
    code = _run(tmp_path, str(folder / "imu.log"), "--dbc", str(folder / "vendor.dbc"),
                *(extra or ("--input", "raw=TPDO2.GyroZ")), "--reference", str(reference), "-o", str(out),
                "--report", str(tmp_path / "r.json"))
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and message in err[0], err
    assert not out.exists() and not (tmp_path / "r.json").exists()


def test_apply_and_noise_read_the_gyro_signal_input_raw_names(vendor_files, tmp_path: Path, capsys) -> None:
    """own-imu.md documents --input raw=MESSAGE.Signal for a CAN log; apply and noise ignored it and
    looked for canical's IMU_RAW ("no IMU_RAW frames in N frames"), so only --config worked."""
    case, folder = vendor_files
    cset = tmp_path / "z.yaml"
    assert _run(folder, str(folder / "imu.log"), "--dbc", str(folder / "vendor.dbc"),
                "--input", "raw=TPDO2.GyroZ", "--reference", str(folder / "table.csv"), "--no-extend",
                "-o", str(cset)) == 0
    capsys.readouterr()
    out = tmp_path / "f.csv"
    vendor = ["--dbc", str(folder / "vendor.dbc"), "--input", "raw=TPDO2.GyroZ"]
    assert main(["apply", str(cset), str(folder / "imu.log"), *vendor, "-o", str(out)]) == 0, \
        capsys.readouterr().err
    table = read_table(out).columns
    assert len(table["raw"]) == len(case.session)
    assert np.allclose(table["raw"], np.round(case.session.raw * 10) / 10)
    assert np.isfinite(table["rate_dps"]).all()
    # Corrected, each of the table's rates is there, to the quantisation (raw alone is 0.3 off).
    for rate in np.unique(case.table.ref_dps):
        assert np.sum(np.abs(table["rate_dps"] - rate) < 0.1) > 50, rate
    capsys.readouterr()
    code = main(["noise", str(folder / "imu.log"), *vendor, "--coefficients", str(cset)])
    err = capsys.readouterr().err
    assert "IMU_RAW" not in err and ("TPDO2" in err or code == 0), err
    # Three axes need three signals: one line that says where they are named.
    code = main(["apply", str(cset), str(folder / "imu.log"), *vendor, "-o", str(tmp_path / "g.csv")])
    assert code == 0


def test_an_imu_set_refuses_one_raw_signal_for_three_axes(vendor_files, tmp_path: Path, capsys) -> None:
    _, folder = vendor_files
    code = _run(folder, str(folder / "imu.log"), str(folder / "imu.log"), str(folder / "imu.log"),
                "--dbc", str(folder / "vendor.dbc"), "--input", "raw=TPDO2.GyroZ",
                "-o", str(tmp_path / "imu.yaml"))
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    assert "--input raw=MESSAGE.Signal names one axis's gyro signal" in err and "--config" in err


def test_apply_refuses_a_set_for_raw_values_in_another_unit(vendor_files, tmp_path: Path, capsys) -> None:
    """A set for counts applied to the vendor's deg/s signal corrected 5.49 to -0.216 deg/s silently."""
    from canical.sets import coefficient_file

    _, folder = vendor_files
    made = tmp_path / "z.yaml"
    assert _run(folder, str(folder / "imu.log"), "--dbc", str(folder / "vendor.dbc"),
                "--input", "raw=TPDO2.GyroZ", "--reference", str(folder / "table.csv"), "--no-extend",
                "-o", str(made)) == 0
    counts = tmp_path / "counts.yaml"
    coefficient_file.save(counts, replace(coefficient_file.load(made), raw_units="counts"))
    capsys.readouterr()
    vendor = ["--dbc", str(folder / "vendor.dbc"), "--input", "raw=TPDO2.GyroZ"]
    out = tmp_path / "f.csv"
    assert main(["apply", str(counts), str(folder / "imu.log"), *vendor, "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip()
    assert err == (f"canical apply: error: {counts}: set is for raw values in counts, the signal is in "
                   "deg/s: calibrate from this signal (a CAN log of it, or a CSV with the line "
                   "'# raw_units: deg/s')")
    assert not out.exists()


def test_a_log_without_the_tables_rate_says_where_it_can_come_from(vendor_files, tmp_path: Path,
                                                                   capsys) -> None:
    _, folder = vendor_files
    code = _run(folder, str(folder / "imu.log"), "--dbc", str(folder / "vendor.dbc"),
                "--input", "raw=TPDO2.GyroZ", "-o", str(tmp_path / "z.yaml"))
    err = capsys.readouterr().err.strip()
    assert code == 2 and len(err.splitlines()) == 1, err
    assert err.endswith("no TPDO2 frames with ref seen in 41000 frames; the table's rate: map it with "
                        "--input ref_dps=MESSAGE.Signal, or give the table's own file with --reference")
