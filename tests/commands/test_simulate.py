"""``canical simulate``: what a user without hardware tries every feature on, in their DBC's layout."""

from __future__ import annotations

import re
from pathlib import Path

import pytest
import yaml

from canical.commands.cli import main
from canical.sessions.csv_file import read_table
from canical.sets import coefficient_file

DATA = Path(__file__).resolve().parents[1] / "data"


def vendor_config(folder: Path) -> Path:
    """A vendor's CANopen IMU (gyro in deg/s at 0.1, temperature in a message of its own)."""
    content = {
        "bus": {"interface": "virtual", "channel": "vendor"},
        "dbc": [str(DATA / "vendor_imu.dbc"), str(DATA / "vendor_imu_ext.dbc")],
        "axes": {"x": {"raw": "GYRO_TPDO2.GyroX"}, "y": {"raw": "GYRO_TPDO2.GyroY"},
                 "z": {"raw": "GYRO_TPDO2.GyroZ", "coefficients": str(folder / "imu-z.yaml")}},
        "inputs": {"temp_c": {"signal": "IMU_TEMP.SensorTemp", "max_age_s": 1.0}},
    }
    path = folder / "vendor.yaml"
    path.write_text(yaml.safe_dump(content, sort_keys=False))
    return path


def test_a_simulated_session_is_calibrated_and_its_effect_found(tmp_path: Path, capsys) -> None:
    session, cset = tmp_path / "s.csv", tmp_path / "z.yaml"
    assert main(["simulate", "session", "-o", str(session)]) == 0
    assert main(["calibrate", str(session), "-o", str(cset)]) == 0, capsys.readouterr().err
    made = coefficient_file.load(cset)
    assert len(made.terms) >= 1 and "temp_c" in repr(made.terms)
    drive, out = tmp_path / "d.csv", tmp_path / "out.csv"
    assert main(["simulate", "drive", "-o", str(drive)]) == 0
    assert main(["apply", str(cset), str(drive), "--track-bias", "-o", str(out)]) == 0
    table = read_table(out).columns
    assert {"time_s", "raw", "temp_c", "speed_mps", "rate_dps", "bias_dps"} <= set(table)
    assert (table["bias_dps"] != 0).any()


def test_a_simulated_triad_calibrates_to_an_imu_set(tmp_path: Path, capsys) -> None:
    folder = tmp_path / "triad"
    assert main(["simulate", "triad", "-o", str(folder)]) == 0
    files = [str(folder / f"{a}.csv") for a in "xyz"]
    assert main(["calibrate", *files, "-o", str(tmp_path / "imu.yaml")]) == 0, capsys.readouterr().err
    assert "IMU set" in capsys.readouterr().out


def test_a_vendor_log_in_the_users_layout_calibrates_and_applies(tmp_path: Path, capsys) -> None:
    """The log holds the vendor's GYRO_TPDO2 and IMU_TEMP frames and canical's TABLE_REF, as
    ``record`` would take them from the bus: calibrate and apply --track-bias read it with the
    configuration alone."""
    config = vendor_config(tmp_path)
    log, cset = tmp_path / "s.log", tmp_path / "imu-z.yaml"
    assert main(["simulate", "session", "--config", str(config), "-o", str(log)]) == 0
    assert main(["calibrate", str(log), "--config", str(config), "--sensor", "SIM-0001",
                 "-o", str(cset)]) == 0, capsys.readouterr().err
    made = coefficient_file.load(cset)
    assert made.raw_units == "deg/s" and "temp_c" in str(made.terms)
    drive, out = tmp_path / "d.log", tmp_path / "out.csv"
    assert main(["simulate", "drive", "--config", str(config), "-o", str(drive)]) == 0
    capsys.readouterr()
    assert main(["apply", str(cset), str(drive), "--config", str(config), "--track-bias",
                 "-o", str(out)]) == 0, capsys.readouterr().err
    assert len(read_table(out).columns["rate_dps"]) > 100_000


@pytest.mark.parametrize("name", ["s.log", "s.asc"])
def test_a_log_without_a_configuration_is_one_line(tmp_path: Path, capsys, name: str) -> None:
    assert main(["simulate", "session", "-o", str(tmp_path / name)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "give --config" in err
    assert not (tmp_path / name).exists()


def test_a_j1939_imus_groups_come_from_its_configured_address(tmp_path: Path) -> None:
    """The vendor's DBC has its default address 0xE2; the configuration says the fitted IMU
    claimed 0x80: the simulated log's groups come from 0x80, as the configuration reads them."""
    import can

    content = {"bus": {"interface": "virtual", "channel": "j"}, "dbc": str(DATA / "vendor_j1939_gyro.dbc"),
               "j1939": {"source_address": 0x80, "messages": ["PGN65335_FF37_Gyro", "PGN65336_FF38_Temp"]},
               "axes": {"z": {"raw": "PGN65335_FF37_Gyro.Gyr_Z", "coefficients": "z.yaml"}},
               "inputs": {"temp_c": {"signal": "PGN65336_FF38_Temp.Temp"}}}
    config, log = tmp_path / "j.yaml", tmp_path / "s.log"
    config.write_text(yaml.safe_dump(content))
    assert main(["simulate", "drive", "--config", str(config), "-o", str(log)]) == 0
    ids = {m.arbitration_id for m, _ in zip(can.LogReader(str(log)), range(2000), strict=False)}
    assert ids == {0x18FF3780, 0x18FF3880}, sorted(map(hex, ids))


def canopen_config(folder: Path, axes: str = "z") -> Path:
    """The CANopen IMU of own-imu.md (Gyr_X, Gyr_Y, Gyr_Z at 0.1 deg/s in TPDO2_Gyro)."""
    content = {"bus": {"interface": "virtual", "channel": "vendor"},
               "dbc": str(DATA / "vendor_canopen_gyro.dbc"),
               "axes": {a: {"raw": f"TPDO2_Gyro.Gyr_{a.upper()}"} for a in axes},
               "inputs": {"temp_c": {"signal": "TPDO3_Temp.Temp", "max_age_s": 1.0}}}
    if axes == "xyz":
        content["imu_set"] = str(folder / "imu.yaml")
    else:
        content["axes"][axes[-1]]["coefficients"] = str(folder / "imu-z.yaml")
    path = folder / f"canopen-{axes}.yaml"
    path.write_text(yaml.safe_dump(content, sort_keys=False))
    return path


def frame_ids(log: Path) -> set[int]:
    import can

    return {m.arbitration_id for m in can.LogReader(str(log))}


def test_a_session_with_the_tables_own_file(tmp_path: Path, capsys) -> None:
    """--table-file: the log holds the IMU's frames alone (no TABLE_REF, 0x120), the table's rate
    is in imu-table.csv on its own clock; calibrate --reference finds that clock (5000.25 s off,
    75 ppm slow) and the temperature effect, as from the log with the table on the bus."""
    config, log = canopen_config(tmp_path), tmp_path / "imu.log"
    assert main(["simulate", "session", "--config", str(config), "--table-file", "-o", str(log)]) == 0
    assert "its own file imu-table.csv" in capsys.readouterr().out
    assert frame_ids(log) == {0x288, 0x388}
    table = read_table(tmp_path / "imu-table.csv").columns
    assert set(table) == {"time_s", "ref_dps"} and 5000.0 < table["time_s"][0] < 5000.6
    cset = tmp_path / "imu-z.yaml"
    assert main(["calibrate", str(log), "--config", str(config), "--reference",
                 str(tmp_path / "imu-table.csv"), "--sensor", "SIM-0001", "-o", str(cset)]) == 0, \
        capsys.readouterr().err
    printed = capsys.readouterr().out
    offset, drift = re.search(r"offset ([\d.]+) s, drift ([-\d.]+) ppm", printed).groups()
    assert abs(float(offset) - 5000.25) < 0.01 and abs(float(drift) + 75.0) < 5.0, printed
    assert "temp_c" in str(coefficient_file.load(cset).terms)


def test_a_triad_of_vendor_logs_with_the_tables_own_files(tmp_path: Path, capsys) -> None:
    """simulate triad --config --table-file: x.log, y.log, z.log (the IMU's frames alone) and the
    table's file beside each; calibrate --reference makes an IMU set whose axes say deg/s (the
    signal's unit), so the daemon's configuration takes it (it refused one that said counts)."""
    config, folder = canopen_config(tmp_path, "xyz"), tmp_path / "logs"
    assert main(["simulate", "triad", "--config", str(config), "--table-file", "-o", str(folder)]) == 0
    assert sorted(p.name for p in folder.iterdir()) == ["x-table.csv", "x.log", "y-table.csv", "y.log",
                                                         "z-table.csv", "z.log"]
    assert frame_ids(folder / "x.log") == {0x288, 0x388}
    logs = [str(folder / f"{a}.log") for a in "xyz"]
    refs = [arg for a in "xyz" for arg in ("--reference", str(folder / f"{a}-table.csv"))]
    capsys.readouterr()
    assert main(["calibrate", *logs, "--config", str(config), *refs, "--sensor", "SIM-TRIAD",
                 "-o", str(tmp_path / "imu.yaml")]) == 0, capsys.readouterr().err
    printed = capsys.readouterr().out
    for a in "xyz":
        assert f"{folder / a}.log: the table turns about IMU axis {a} (" in printed
    assert (tmp_path / "imu.yaml").read_text().count("units: {raw: deg/s") == 3
    assert main(["serve", "--config", str(config), "--check"]) == 0, capsys.readouterr().err


def test_a_triad_log_with_the_table_on_the_bus(tmp_path: Path, capsys) -> None:
    """Without --table-file each log carries TABLE_REF naming the axis: calibrate reads it alone."""
    config, folder = canopen_config(tmp_path, "xyz"), tmp_path / "logs"
    assert main(["simulate", "triad", "--config", str(config), "-o", str(folder)]) == 0
    assert sorted(p.name for p in folder.iterdir()) == ["x.log", "y.log", "z.log"]
    assert frame_ids(folder / "y.log") == {0x120, 0x288, 0x388}
    logs = [str(folder / f"{a}.log") for a in "xyz"]
    assert main(["calibrate", *logs, "--config", str(config), "-o", str(tmp_path / "imu.yaml")]) == 0, \
        capsys.readouterr().err
    assert "IMU set" in capsys.readouterr().out


@pytest.mark.parametrize(("argv", "message"), [
    (["drive", "--table-file", "-o", "d.log"], "--table-file: a drive has no rate table"),
    (["session", "--table-file", "-o", "s.log"], "--table-file: the table's file goes beside a CAN log"),
    (["session", "--table-file", "-o", "s.csv", "CONFIG"], "--table-file: s.csv is a CSV"),
    (["triad", "-o", "logs", "CONFIG"], "a triad needs axes x, y and z named (axes.AXIS.raw); x, y missing"),
])
def test_what_cannot_be_simulated_is_one_line(tmp_path: Path, monkeypatch, capsys, argv, message) -> None:
    monkeypatch.chdir(tmp_path)
    if "CONFIG" in argv:
        argv = [*(a for a in argv if a != "CONFIG"), "--config", str(canopen_config(tmp_path))]
    assert main(["simulate", *argv]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and message in err, err
    assert not any(p.suffix in (".log", ".csv") for p in tmp_path.rglob("*"))
