"""A vendor's IMU in the daemon's configuration: its DBCs beside canical's, axes from any message."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
import yaml
from support.daemon_fixtures import TERMS, write_sets

from canical.bus.daemon_config import load_config
from canical.commands.cli import main
from canical.frames import dbc_files
from canical.sets import coefficient_file

DATA = Path(__file__).resolve().parents[1] / "data"
VENDOR, VENDOR_EXT = DATA / "vendor_imu.dbc", DATA / "vendor_imu_ext.dbc"


@pytest.fixture(scope="module")
def sets(tmp_path_factory) -> dict[str, Path]:
    """Sets with a temperature term on x (the vendor's IMU_TEMP feeds it)."""
    return write_sets(tmp_path_factory.mktemp("sets"), terms={"x": TERMS["x"][:1], "y": (), "z": ()},
                      raw_units="deg/s")


@pytest.fixture(autouse=True)
def _fresh_warnings(monkeypatch):
    monkeypatch.setattr(dbc_files, "_WARNED", set())


def vendor_config(folder: Path, sets: dict[str, Path], **changes) -> Path:
    content = {
        "bus": {"interface": "virtual", "channel": "vendor"},
        "dbc": [str(VENDOR), str(VENDOR_EXT)],
        "axes": {a: {"raw": f"GYRO_TPDO2.Gyro{a.upper()}", "coefficients": str(sets[a])} for a in "xyz"},
        "inputs": {"temp_c": {"signal": "IMU_TEMP.SensorTemp", "max_age_s": 1.0}},
    }
    content.update(changes)
    path = folder / "vendor.yaml"
    path.write_text(yaml.safe_dump(content, sort_keys=False))
    return path


def test_a_vendor_imu_from_its_own_dbcs_standard_id_no_counter(tmp_path, sets, capsys) -> None:
    config = load_config(vendor_config(tmp_path, sets))
    assert config.raw_message == "GYRO_TPDO2" and config.counter_signal is None
    assert [a.raw_signal for a in config.axes] == ["GyroX", "GyroY", "GyroZ"]
    assert (config.rate_message, config.status_message) == ("CANICAL_RATE", "CANICAL_STATUS")
    assert [p.name for p in config.dbc_path] == ["vendor_imu.dbc", "vendor_imu_ext.dbc"]
    assert main(["serve", "--config", str(tmp_path / "vendor.yaml"), "--check"]) == 0
    assert "configuration OK" in capsys.readouterr().out


def test_a_vendor_imu_on_an_extended_id_with_motorola_signals(tmp_path, sets) -> None:
    axes = {a: {"raw": f"ANGRATE.{s}", "coefficients": str(sets[a])}
            for a, s in zip("xyz", ("RollRate", "PitchRate", "YawRate"), strict=True)}
    config = load_config(vendor_config(tmp_path, sets, axes=axes, dbc=str(VENDOR_EXT), counter="RateStatus"))
    assert config.raw_message == "ANGRATE" and config.counter_signal == "RateStatus"
    assert config.inputs["temp_c"].message == "IMU_TEMP"


@pytest.mark.parametrize(
    ("change", "key", "words"),
    [
        ({"inputs": {"hud": {"signal": "HUD_ODD.HudTemp"}}}, "inputs.hud.signal", "HUD_ODD is broken"),
        ({"axes": {"x": {"raw": "CANICAL_RATE.RateX", "coefficients": "x.yaml"},
                   "y": {"raw": "GYRO_TPDO2.GyroY"}, "z": {"raw": "GYRO_TPDO2.GyroZ"}}}, "axes.x.raw",
         "cannot come from a frame the daemon sends"),
        ({"axes": {"x": {"raw": "GYRO_TPDO2.GyroQ", "coefficients": "x.yaml"}}}, "axes.x.raw", "GyroQ"),
        ({"dbc": []}, "dbc", "empty list"),
        ({"dbc": [str(VENDOR), "missing.dbc"]}, "dbc[1]", "not found"),
        ({"counter": "Counter"}, "counter", "signal Counter not in message GYRO_TPDO2"),
    ],
)
def test_bad_vendor_configuration_is_one_line_exit_2(tmp_path, sets, capsys, change, key, words) -> None:
    path = vendor_config(tmp_path, sets, **change)
    assert main(["serve", "--config", str(path), "--check"]) == 2
    out = capsys.readouterr()
    lines = out.err.strip().splitlines()
    assert lines[-1].startswith(f"error: {path}: {key}: ") or f"{path}: {key}: " in lines[-1], out.err
    assert words in lines[-1] and not out.out
    assert all("warning" in line for line in lines[:-1])


def test_two_dbcs_defining_a_message_differently_are_one_line_naming_both(tmp_path, sets, capsys) -> None:
    other = tmp_path / "other.dbc"
    other.write_text('VERSION ""\n\nNS_ :\n\nBS_:\n\nBU_: A\n\n'
                     'BO_ 648 GYRO_TPDO2: 6 A\n SG_ GyroX : 0|16@1- (0.01,0) [0|0] "" A\n')
    path = vendor_config(tmp_path, sets, dbc=[str(VENDOR), str(other)])
    assert main(["serve", "--config", str(path), "--check"]) == 2
    line = capsys.readouterr().err.strip().splitlines()[-1]
    assert "GYRO_TPDO2" in line and "vendor_imu.dbc" in line and "other.dbc" in line


def test_dbc_is_repeatable_on_the_verbs_that_read_logs() -> None:
    import argparse

    from canical.commands.canlog_args import add_canlog_arguments, canlog_source

    parser = argparse.ArgumentParser()
    add_canlog_arguments(parser)
    source = canlog_source(parser.parse_args(["--dbc", str(VENDOR), "--dbc", str(VENDOR_EXT)]), "drive.log")
    assert list(source.dbc) == [VENDOR, VENDOR_EXT] and str(source.dbc) == f"{VENDOR} + {VENDOR_EXT}"


def test_a_set_for_raw_values_in_another_unit_is_refused(tmp_path, sets, capsys) -> None:
    """The vendor's signals are in deg/s: a set made for raw values in mV is for another signal."""
    mv = tmp_path / "y-mv.yaml"
    coefficient_file.save(mv, replace(coefficient_file.load(sets["y"]), raw_units="mV"))
    axes = {a: {"raw": f"GYRO_TPDO2.Gyro{a.upper()}", "coefficients": str(mv if a == "y" else sets[a])}
            for a in "xyz"}
    assert main(["serve", "--config", str(vendor_config(tmp_path, sets, axes=axes)), "--check"]) == 2
    errors = [line for line in capsys.readouterr().err.splitlines() if "warning" not in line]
    assert len(errors) == 1 and errors[0].endswith(
        "axis y: set is for raw values in mV, the signal is in deg/s: calibrate from this signal (a CAN "
        "log of it, or a CSV with the line '# raw_units: deg/s')"), errors


def test_a_set_for_counts_is_refused_on_a_signal_in_deg_s(tmp_path, sets, capsys) -> None:
    """own-imu.md: serve refuses a set made for raw values in another unit. A set that says counts
    (canical's default for a CSV) passed on the vendor's deg/s signal, and corrected 5.49 deg/s to
    -0.216 deg/s without a word."""
    counts = tmp_path / "y-counts.yaml"
    coefficient_file.save(counts, replace(coefficient_file.load(sets["y"]), raw_units="counts"))
    axes = {a: {"raw": f"GYRO_TPDO2.Gyro{a.upper()}", "coefficients": str(counts if a == "y" else sets[a])}
            for a in "xyz"}
    assert main(["serve", "--config", str(vendor_config(tmp_path, sets, axes=axes)), "--check"]) == 2
    errors = [line for line in capsys.readouterr().err.splitlines() if "warning" not in line]
    assert len(errors) == 1 and "set is for raw values in counts, the signal is in deg/s" in errors[0], errors


def test_a_missing_set_names_the_key_that_points_at_it(tmp_path, sets, capsys) -> None:
    axes = {a: {"raw": f"GYRO_TPDO2.Gyro{a.upper()}",
                "coefficients": str(tmp_path / "nowhere.yaml" if a == "y" else sets[a])} for a in "xyz"}
    config = vendor_config(tmp_path, sets, axes=axes)
    assert main(["serve", "--config", str(config), "--check"]) == 2
    errors = [line for line in capsys.readouterr().err.splitlines() if "warning" not in line]
    assert errors == [f"canical serve: error: {tmp_path / 'nowhere.yaml'}: coefficient file not found "
                      f"(axes.y.coefficients in {config})"]
