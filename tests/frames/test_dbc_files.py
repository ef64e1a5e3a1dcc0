"""DBC files as vendors and vehicles write them: non-strict, several files, canical's frames beside."""

from __future__ import annotations

from pathlib import Path

import pytest

from canical.errors import CanicalError
from canical.frames import dbc_files
from canical.frames.dbc_files import DbcSet, load_dbc, require_sound

DATA = Path(__file__).resolve().parents[1] / "data"
VENDOR, VENDOR_EXT = DATA / "vendor_imu.dbc", DATA / "vendor_imu_ext.dbc"


@pytest.fixture(autouse=True)
def _fresh_warnings(monkeypatch):
    monkeypatch.setattr(dbc_files, "_WARNED", set())


def test_a_file_cantools_loads_only_non_strictly_loads_and_names_the_relaxed_message_once(capsys) -> None:
    db = load_dbc(VENDOR)
    names = {m.name for m in db.messages}
    assert {"GYRO_TPDO2", "HUD_ODD", "CANICAL_RATE", "CANICAL_STATUS", "TABLE_REF"} <= names
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "HUD_ODD" in err[0] and "vendor_imu.dbc" in err[0] and "GYRO_TPDO2" not in err[0]
    load_dbc(VENDOR)
    assert capsys.readouterr().err == ""  # once
    require_sound(db.get_message_by_name("GYRO_TPDO2"), "x")
    with pytest.raises(CanicalError, match=r"^x: message HUD_ODD is broken \(The signals .* overlapping"):
        require_sound(db.get_message_by_name("HUD_ODD"), "x")


def test_several_files_are_merged_with_extended_ids_and_canicals_frames() -> None:
    db = load_dbc(DbcSet((VENDOR, VENDOR_EXT)))
    angrate = db.get_message_by_name("ANGRATE")
    assert angrate.is_extended_frame and angrate.frame_id == 0x18FF2A10
    assert db.get_message_by_name("GYRO_TPDO2").frame_id == 0x288
    assert db.get_message_by_name("CANICAL_RATE").frame_id == 0x110
    assert db.get_message_by_frame_id(0x110).name == "CANICAL_RATE"
    # The shipped file named by the user too: the same messages, no conflict.
    assert len(load_dbc([VENDOR, dbc_files.shipped_dbc_path()]).messages) == len(load_dbc(VENDOR).messages)


def _write(path: Path, body: str) -> Path:
    path.write_text('VERSION ""\n\nNS_ :\n\nBS_:\n\nBU_: A\n\n' + body + "\n")
    return path


def test_a_message_defined_differently_in_two_files_is_one_line_naming_both(tmp_path) -> None:
    other = _write(tmp_path / "other.dbc",
                   'BO_ 648 GYRO_TPDO2: 6 A\n SG_ GyroX : 0|16@1- (0.01,0) [0|0] "" A\n')
    with pytest.raises(CanicalError) as exc:
        load_dbc([VENDOR, other])
    text = str(exc.value)
    assert "\n" not in text and "GYRO_TPDO2" in text and str(VENDOR) in text and str(other) in text


def test_an_id_two_files_give_different_names_is_one_line_naming_both(tmp_path) -> None:
    other = _write(tmp_path / "other.dbc", 'BO_ 648 SOMETHING: 2 A\n SG_ S : 0|8@1+ (1,0) [0|0] "" A\n')
    with pytest.raises(CanicalError, match=r"^id 0x288 is GYRO_TPDO2 in .*vendor_imu.dbc and SOMETHING in "):
        load_dbc([VENDOR, other])


def test_a_users_own_canical_rate_wins_over_the_shipped_one(tmp_path) -> None:
    own = _write(tmp_path / "own.dbc", 'BO_ 272 CANICAL_RATE: 2 A\n SG_ RateX : 0|16@1- (0.1,0) [0|0] "" A\n')
    db = load_dbc(own)
    assert db.get_message_by_name("CANICAL_RATE").length == 2


def test_a_missing_or_unreadable_file_is_one_line(tmp_path) -> None:
    with pytest.raises(CanicalError, match="DBC file not found"):
        load_dbc([VENDOR, tmp_path / "nope.dbc"])
    bad = tmp_path / "bad.dbc"
    bad.write_text("BO_ this is not a dbc\n")
    with pytest.raises(CanicalError, match="not a valid DBC file"):
        load_dbc(bad)
