"""A daemon with ``trust: {require: true}`` and ``device:`` verifies the device's sets as it does a
file's: the signature each bank carries (an IMU set's, on its coupling bank) must be a trusted
key's over the bytes the device holds, for its sensor, and not older than the running set. A
device set that verifies is adopted (source: the device, its signed version); one that does not
(unsigned, another key) is refused with one warning and the signed files are used (in-process, the
emulated IMU on python-can's virtual bus, as ``test_imu_set_device``)."""

from __future__ import annotations

from pathlib import Path

from support.daemon_fixtures import write_config
from support.imu_fixtures import imu_triad_set
from support.signed_sets import make_lab, signed_copy
from test_imu_set_device import AXES, NODE, bus, emulated

from canical.bus import active_sets
from canical.bus.daemon_config import load_config
from canical.commands.cli import main
from canical.sets import imu_set as imu_file


def daemon_sets(tmp_path: Path, channel: str, lab_pub: Path) -> tuple[active_sets.ActiveSets, list]:
    cfg = write_config(tmp_path, channel, interface="virtual", sensor=None, inputs={},
                       device={"node": NODE, "timeout_s": 2.0},
                       axes={a: {"raw": f"GyroRaw{a.upper()}"} for a in AXES},
                       imu_set=str(tmp_path / "file.yaml"),
                       trust={"keys": [str(lab_pub)]})
    return active_sets.initial(load_config(cfg))


def test_the_devices_unsigned_sets_are_refused_and_the_signed_file_used(tmp_path: Path) -> None:
    lab = make_lab(tmp_path / "keys")
    on_device, on_file = imu_triad_set(0), imu_triad_set(1)
    imu_file.save(tmp_path / "device.yaml", on_device)
    imu_file.save(tmp_path / "unsigned.yaml", on_file)
    signed_copy(tmp_path / "unsigned.yaml", tmp_path / "file.yaml", lab.key, 1)
    with emulated(tmp_path) as (_, channel):
        assert main(["push", str(tmp_path / "device.yaml"), *bus(channel)]) == 0
        sets, notes = daemon_sets(tmp_path, channel, lab.pub)
    assert sets.combined_id == imu_file.imu_set_crc(on_file) and sets.complete
    assert [ax.source for ax in sets.axes] == [active_sets.SOURCE_FILE] * 3
    assert [ax.version for ax in sets.axes] == [1, 1, 1]
    refused = [n.text for n in notes if n.refused]
    assert len(refused) == 1 and "not signed" in refused[0] and "\n" not in refused[0], notes


def test_the_devices_set_signed_by_another_key_is_refused(tmp_path: Path) -> None:
    lab = make_lab(tmp_path / "keys")
    imu_file.save(tmp_path / "unsigned.yaml", imu_triad_set(1))
    signed_copy(tmp_path / "unsigned.yaml", tmp_path / "file.yaml", lab.key, 1)
    imu_file.save(tmp_path / "device.yaml", imu_triad_set(0))
    signed_copy(tmp_path / "device.yaml", tmp_path / "stranger.yaml", lab.other_key, 2)
    with emulated(tmp_path) as (_, channel):
        assert main(["push", str(tmp_path / "stranger.yaml"), *bus(channel)]) == 0
        sets, notes = daemon_sets(tmp_path, channel, lab.pub)
    assert [ax.source for ax in sets.axes] == [active_sets.SOURCE_FILE] * 3
    refused = [n.text for n in notes if n.refused]
    assert len(refused) == 1 and "not trusted" in refused[0], notes


def test_the_devices_signed_set_is_adopted(tmp_path: Path) -> None:
    lab = make_lab(tmp_path / "keys")
    on_device, on_file = imu_triad_set(0), imu_triad_set(1)
    imu_file.save(tmp_path / "unsigned.yaml", on_file)
    signed_copy(tmp_path / "unsigned.yaml", tmp_path / "file.yaml", lab.key, 1)
    imu_file.save(tmp_path / "device.yaml", on_device)
    signed_copy(tmp_path / "device.yaml", tmp_path / "signed.yaml", lab.key, 3)
    with emulated(tmp_path) as (_, channel):
        assert main(["push", str(tmp_path / "signed.yaml"), *bus(channel)]) == 0
        sets, notes = daemon_sets(tmp_path, channel, lab.pub)
    assert sets.combined_id == imu_file.imu_set_crc(on_device) and sets.complete
    assert [ax.source for ax in sets.axes] == [active_sets.SOURCE_DEVICE] * 3
    assert [ax.version for ax in sets.axes] == [3, 3, 3]
    assert not [n for n in notes if n.refused], notes


def single_axis_sets(tmp_path: Path, lab, *, signed_on_device: bool) -> tuple[active_sets.ActiveSets, list]:
    """Single-axis sets on the device (signed as version 4, or not) and signed files (version 1)."""
    from support.imu_fixtures import imu_set

    from canical.sets import coefficient_file

    pushed = []
    for axis in AXES:
        coefficient_file.save(tmp_path / f"plain-{axis}.yaml", imu_set(axis, family=1))
        signed_copy(tmp_path / f"plain-{axis}.yaml", tmp_path / f"imu-{axis}.yaml", lab.key, 1)
        coefficient_file.save(tmp_path / f"device-{axis}.yaml", imu_set(axis))
        if signed_on_device:
            signed_copy(tmp_path / f"device-{axis}.yaml", tmp_path / f"signed-{axis}.yaml", lab.key, 4)
        pushed.append(str(tmp_path / f"{'signed' if signed_on_device else 'device'}-{axis}.yaml"))
    with emulated(tmp_path) as (_, channel):
        assert main(["push", *pushed, *bus(channel)]) == 0
        cfg = write_config(tmp_path, channel, interface="virtual", sensor=None, inputs={},
                           device={"node": NODE, "timeout_s": 2.0},
                           axes={a: {"raw": f"GyroRaw{a.upper()}",
                                     "coefficients": str(tmp_path / f"imu-{a}.yaml")} for a in AXES},
                           trust={"keys": [str(lab.pub)]})
        return active_sets.initial(load_config(cfg))


def test_the_devices_signed_single_axis_sets_are_adopted_and_unsigned_ones_refused(tmp_path: Path) -> None:
    lab = make_lab(tmp_path / "keys")
    (tmp_path / "signed").mkdir()
    sets, notes = single_axis_sets(tmp_path / "signed", lab, signed_on_device=True)
    assert [ax.source for ax in sets.axes] == [active_sets.SOURCE_DEVICE] * 3
    assert [ax.version for ax in sets.axes] == [4, 4, 4] and not [n for n in notes if n.refused], notes
    (tmp_path / "unsigned").mkdir()
    sets, notes = single_axis_sets(tmp_path / "unsigned", lab, signed_on_device=False)
    assert [ax.source for ax in sets.axes] == [active_sets.SOURCE_FILE] * 3
    assert [ax.version for ax in sets.axes] == [1, 1, 1]
    refused = [n.text for n in notes if n.refused]
    assert len(refused) == 1 and "not signed" in refused[0], notes
