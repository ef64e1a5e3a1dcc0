"""`canical calibrate` and `canical apply` as a user runs them: files in, files out, clear errors."""

import json
import re
import subprocess
import sys

import numpy as np
import pytest
from support.sessions import write_session

from canical.commands.cli import main
from canical.sessions.csv_file import read_session, read_table
from canical.sim.sessions import paper_session


@pytest.fixture(scope="module")
def session_csv(tmp_path_factory):
    return write_session(tmp_path_factory.mktemp("s") / "session.csv", paper_session(seed=5))


def test_calibrate_then_apply(session_csv, tmp_path, capsys):
    coeffs, report, out = tmp_path / "c.yaml", tmp_path / "r.json", tmp_path / "out.csv"
    assert main(["calibrate", str(session_csv), "-o", str(coeffs), "--report", str(report)]) == 0
    rep = json.loads(report.read_text())
    for key in ("model", "segment_points", "training", "held_out", "effects", "samples"):
        assert key in rep
    assert rep["effects"] == []
    assert rep["samples"]["used"] < rep["samples"]["total"]
    assert rep["held_out"]["rms_dps"] < 0.02
    assert main(["apply", str(coeffs), str(session_csv), "-o", str(out)]) == 0
    text_in = session_csv.read_text().splitlines()
    text_out = out.read_text().splitlines()
    assert len(text_in) == len(text_out)
    # Rows are echoed unchanged with the two new columns appended.
    assert text_out[2] == text_in[2] + ",rate_dps,out_of_span"
    assert all(o.startswith(i + ",") for i, o in zip(text_in[3:50], text_out[3:50], strict=True))
    table = read_table(out).columns
    settled = np.abs(table["rate_dps"] - table["ref_dps"]) < 0.5
    assert settled.mean() > 0.85  # all but ramps and the sensor's lag
    assert "rows corrected" in capsys.readouterr().out


@pytest.mark.parametrize("model", ["segmented-linear", "forward-poly", "segmented-inverse"])
def test_every_model_round_trips_through_files(model, session_csv, tmp_path):
    coeffs = tmp_path / "c.yaml"
    assert main(["calibrate", str(session_csv), "-o", str(coeffs), "--model", model]) == 0
    assert main(["apply", str(coeffs), str(session_csv), "-o", str(tmp_path / "o.csv")]) == 0


def test_apply_never_reads_the_reference_column(session_csv, tmp_path):
    coeffs = tmp_path / "c.yaml"
    main(["calibrate", str(session_csv), "-o", str(coeffs), "--segments", "3", "--order", "2"])
    lines = session_csv.read_text().splitlines()
    scrambled = [lines[0], lines[1], lines[2]] + [
        ",".join([c if i != 1 else "not-a-number" for i, c in enumerate(row.split(","))]) for row in lines[3:]
    ]
    field = tmp_path / "field.csv"
    field.write_text("\n".join(scrambled) + "\n")
    assert main(["apply", str(coeffs), str(field), "-o", str(tmp_path / "a.csv")]) == 0
    assert main(["apply", str(coeffs), str(session_csv), "-o", str(tmp_path / "b.csv")]) == 0
    rate_a = np.loadtxt(tmp_path / "a.csv", delimiter=",", skiprows=3, usecols=3)
    rate_b = np.loadtxt(tmp_path / "b.csv", delimiter=",", skiprows=3, usecols=3)
    np.testing.assert_array_equal(rate_a, rate_b)


def test_renamed_columns(session_csv, tmp_path):
    lines = session_csv.read_text().splitlines()
    lines[2] = "time_s,table,gyro_z"
    renamed = tmp_path / "renamed.csv"
    renamed.write_text("\n".join(lines) + "\n")
    code = main(["calibrate", str(renamed), "-o", str(tmp_path / "c.yaml"),
                 "--raw-column", "gyro_z", "--ref-column", "table"])
    assert code == 0


BAD_INPUTS = {
    "missing column": ("time_s,ref_dps\n0,0\n", "missing column 'raw'"),
    "non-numeric": ("time_s,ref_dps,raw\n0,0,12\n0.1,0,x7\n", "line 3, column raw: 'x7' is not a number"),
    "nan": ("time_s,ref_dps,raw\n0,0,12\n0.1,0,nan\n", "line 3, column raw: value is not finite"),
    "empty": ("", "empty file"),
    "header only": ("time_s,ref_dps,raw\n", "no data rows"),
    "ragged": ("time_s,ref_dps,raw\n0,0,12\n0.1,0\n", "line 3: 2 cells, header has 3"),
}


@pytest.mark.parametrize("case", sorted(BAD_INPUTS))
def test_bad_session_files_fail_with_one_line_and_status_2(case, tmp_path):
    text, message = BAD_INPUTS[case]
    bad = tmp_path / "bad.csv"
    bad.write_text(text)
    out = tmp_path / "c.yaml"
    proc = subprocess.run([sys.executable, "-m", "canical", "calibrate", str(bad), "-o", str(out)],
                          capture_output=True, text=True)
    assert proc.returncode == 2
    assert message in proc.stderr
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    assert not out.exists()
    assert list(tmp_path.iterdir()) == [bad]


def test_no_zero_rate_plateau(tmp_path):
    session = paper_session()
    keep = session.ref_dps != 0
    path = write_session(tmp_path / "s.csv", session.take(keep))
    assert main(["calibrate", str(path), "-o", str(tmp_path / "c.yaml")]) == 2


def test_too_few_plateaus(tmp_path):
    from canical.sim.gyro import GyroModel
    from canical.sim.sessions import sweep_session
    path = write_session(tmp_path / "s.csv", sweep_session(GyroModel(), np.array([0.0, 10.0, 20.0])))
    assert main(["calibrate", str(path), "-o", str(tmp_path / "c.yaml")]) == 2


def test_apply_refuses_a_set_for_another_sensor(session_csv, tmp_path, capsys):
    coeffs = tmp_path / "c.yaml"
    main(["calibrate", str(session_csv), "-o", str(coeffs), "--segments", "2", "--order", "2"])
    other = read_session(session_csv)
    other.meta["sensor"] = "OTHER-9"
    path = write_session(tmp_path / "other.csv", other)
    out = tmp_path / "o.csv"
    assert main(["apply", str(coeffs), str(path), "-o", str(out)]) == 2
    assert "is for sensor SIM-0001" in capsys.readouterr().err
    assert not out.exists()
    assert main(["apply", str(coeffs), str(path), "-o", str(out), "--sensor", "SIM-0001"]) == 0


def test_apply_refuses_a_damaged_set(session_csv, tmp_path, capsys):
    coeffs = tmp_path / "c.yaml"
    main(["calibrate", str(session_csv), "-o", str(coeffs), "--segments", "2", "--order", "2"])
    coeffs.write_text(coeffs.read_text().replace("v0: ", "v0: 1"))
    assert main(["apply", str(coeffs), str(session_csv), "-o", str(tmp_path / "o.csv")]) == 2
    assert "CRC mismatch" in capsys.readouterr().err


def test_existing_output_survives_a_failed_run(session_csv, tmp_path):
    coeffs = tmp_path / "c.yaml"
    coeffs.write_text("previous content\n")
    bad = tmp_path / "bad.csv"
    bad.write_text("time_s,ref_dps,raw\n0,0,oops\n")
    assert main(["calibrate", str(bad), "-o", str(coeffs)]) == 2
    assert coeffs.read_text() == "previous content\n"


def test_demo_runs(tmp_path, capsys):
    assert main(["demo", "--out", str(tmp_path / "demo")]) == 0
    out = capsys.readouterr().out
    assert "lower rms" in out
    # One scheme, one number: the written set scores what its row in the table says.
    row = next(line for line in out.splitlines() if "auto size" in line).split()
    written = re.search(r"the written set on the second session: held-out rms (\d\.\d{4}), "
                        r"max (\d\.\d{4})", out)
    assert written is not None and written.groups() == (row[-2], row[-1])
    assert (tmp_path / "demo" / "coefficients.yaml").exists()
    # The IMU as three axes: the coupling brings the multi-axis error down by well over 10x.
    triad = re.search(r"each axis's set alone (\d+\.\d{4}) deg/s, with the coupling (\d\.\d{4}) deg/s", out)
    assert triad is not None, out
    before, after = (float(v) for v in triad.groups())
    assert after <= 0.01 and before >= 10 * after
    from canical.sets import imu_set

    assert imu_set.load(tmp_path / "demo" / "triad" / "imu.yaml").coupling
    assert (tmp_path / "demo" / "triad" / "report" / "coupling.png").exists()
