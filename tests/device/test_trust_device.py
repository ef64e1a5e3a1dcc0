"""A daemon with ``trust: {require: true}`` and ``device:`` does not take the device's sets: their
bank payloads carry no signature yet, so whatever a node wrote into the IMU over SDO is refused
with one warning and the signed files are used (in-process, the emulated IMU on python-can's
virtual bus, as ``test_imu_set_device``)."""

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


def test_the_devices_unsigned_sets_are_refused_and_the_signed_file_used(tmp_path: Path) -> None:
    lab = make_lab(tmp_path / "keys")
    on_device, on_file = imu_triad_set(0), imu_triad_set(1)
    imu_file.save(tmp_path / "device.yaml", on_device)
    imu_file.save(tmp_path / "unsigned.yaml", on_file)
    signed_copy(tmp_path / "unsigned.yaml", tmp_path / "file.yaml", lab.key, 1)
    with emulated(tmp_path) as (_, channel):
        assert main(["push", str(tmp_path / "device.yaml"), *bus(channel)]) == 0
        cfg = write_config(tmp_path, channel, interface="virtual", sensor=None, inputs={},
                           device={"node": NODE, "timeout_s": 2.0},
                           axes={a: {"raw": f"GyroRaw{a.upper()}"} for a in AXES},
                           imu_set=str(tmp_path / "file.yaml"),
                           trust={"keys": [str(lab.pub)]})
        sets, notes = active_sets.initial(load_config(cfg))
    assert sets.combined_id == imu_file.imu_set_crc(on_file) and sets.complete
    assert [ax.source for ax in sets.axes] == [active_sets.SOURCE_FILE] * 3
    assert [ax.version for ax in sets.axes] == [1, 1, 1]
    refused = [n.text for n in notes if n.refused]
    assert len(refused) == 1 and "carry no signature" in refused[0], notes
