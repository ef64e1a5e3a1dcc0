"""`canical export dcf`: the IMU's EDS with the sets' bank values, for any CANopen tool.

Loaded back with canopen's own object-dictionary import, and downloaded to the emulated IMU
as a configuration tool does it: every writable object with a ParameterValue, in index order,
by plain canopen SDO writes (no canical code on the writing side). canopen's own
``RemoteNode.load_configuration`` would do the same but first rewrites every PDO's parameters,
which an IMU with fixed PDOs (this one) refuses.
"""

from __future__ import annotations

import contextlib
import subprocess
import sys
import uuid
from collections.abc import Iterator
from pathlib import Path

import canopen
import pytest
from canopen.sdo import SdoAbortedError
from support.imu_fixtures import SERIAL, imu_set, imu_sets

from canical.device.bank_payload import encode_set
from canical.device.emulated_imu import EmulatedImu, EmulatorConfig
from canical.device.sdo_download import ImuClient, push_sets
from canical.frames.imu_dictionary import (
    AXES,
    STORE_SIGNATURE,
    eds_path,
    imu_objects,
    object_dictionary,
    pack_active,
)
from canical.sets import coefficient_file

NODE = 0x10


def export(
    tmp_path: Path, sets: dict, *extra: str, name: str = "imu.dcf"
) -> tuple[Path, subprocess.CompletedProcess]:
    paths = []
    for axis, cset in sets.items():
        path = tmp_path / f"imu-{axis}-{uuid.uuid4().hex[:6]}.yaml"
        coefficient_file.save(path, cset)
        paths.append(str(path))
    out = tmp_path / name
    done = subprocess.run([sys.executable, "-m", "canical", "export", "dcf", *paths, "-o", str(out), *extra],
                          capture_output=True, text=True, check=False)  # fmt: skip
    return out, done


def variables(od: canopen.ObjectDictionary) -> dict[tuple[int, int], canopen.objectdictionary.ODVariable]:
    out = {}
    for obj in od.values():
        members = obj.values() if not isinstance(obj, canopen.objectdictionary.ODVariable) else [obj]
        for var in members:
            out[(var.index, var.subindex)] = var
    return out


def test_dcf_loads_back_with_every_value(tmp_path: Path) -> None:
    sets = imu_sets()
    dcf, done = export(tmp_path, sets, "--node", "0x22", "--bank", "B")
    assert done.returncode == 0, done.stderr
    assert "0x22" in done.stdout and "bank B" in done.stdout
    loaded = canopen.import_od(str(dcf), 0x22)
    assert loaded.node_id == 0x22 and loaded.bitrate == 500_000
    eds = variables(object_dictionary(0x22))
    back = variables(loaded)
    assert back.keys() == eds.keys()
    o = imu_objects()
    expected: dict[tuple[int, int], object] = {o.active_banks: pack_active(dict.fromkeys(AXES, "B"))}
    for axis, cset in sets.items():
        ref = o.bank(axis, "B")
        content, crc = encode_set(cset)
        expected[(ref.index, ref.content)] = content
        expected[(ref.index, ref.crc)] = crc
    for key, var in back.items():
        original = eds[key]
        assert (var.name, var.data_type, var.access_type, var.default) == (
            original.name, original.data_type, original.access_type, original.default), key  # fmt: skip
        assert var.value == expected.get(key), f"0x{key[0]:04x} sub {key[1]}"
    # the DCF is the EDS plus values: nothing else in the text changed
    eds_lines = [ln for ln in eds_path().read_text().splitlines() if not ln.startswith("FileName=")]
    dcf_lines = [ln for ln in dcf.read_text().splitlines() if not ln.startswith("FileName=")]
    assert [ln for ln in dcf_lines if ln not in eds_lines and not ln.startswith("ParameterValue=")] == [
        "[DeviceComissioning]", "NodeID=0x22", "NodeName=canical IMU", "Baudrate=500", "NetNumber=1",
        "NetworkName=canical", "CANopenManager=0"]  # fmt: skip


def test_export_refuses_what_push_refuses(tmp_path: Path) -> None:
    _, two = export(tmp_path, {"z": imu_set("z"), "z2": imu_set("z")})
    assert two.returncode == 2 and "both for axis z" in two.stderr and "Traceback" not in two.stderr
    _, named = export(tmp_path, {"z": imu_set("z", sensor="bench-7")})
    assert named.returncode == 2 and "not an IMU serial number" in named.stderr
    assert "calibrate with --sensor SERIAL" in named.stderr and "canical serve" in named.stderr
    assert len(named.stderr.strip().splitlines()) == 1
    out, ok = export(tmp_path, {"z": imu_set("z")}, "--node", "200")
    assert ok.returncode == 2 and "1..127" in ok.stderr and not out.exists()


def test_the_rated_range_checked_can_be_the_devices_own(tmp_path: Path) -> None:
    """The EDS's default (50 deg/s) unless --rated-range gives the device's configured one."""
    out, wide = export(tmp_path, {"z": imu_set("z")}, "--rated-range", "70")
    assert wide.returncode == 2 and "does not cover the rated range ±70 deg/s (--rated-range)" in wide.stderr
    assert not out.exists()
    out, ok = export(tmp_path, {"z": imu_set("z")}, "--rated-range", "60")
    assert ok.returncode == 0, ok.stderr


@contextlib.contextmanager
def emulated(tmp_path: Path, name: str) -> Iterator[tuple[EmulatedImu, str]]:
    channel = f"dcf-{uuid.uuid4().hex}"
    net = canopen.Network()
    net.connect(interface="virtual", channel=channel, receive_own_messages=False)
    try:
        yield (
            EmulatedImu(EmulatorConfig(node_id=NODE, serial=SERIAL, state_path=tmp_path / name), net),
            channel,
        )
    finally:
        net.disconnect()


@contextlib.contextmanager
def writer(channel: str, dcf: Path | None = None) -> Iterator[canopen.Network]:
    net = canopen.Network()
    net.connect(interface="virtual", channel=channel, receive_own_messages=False)
    try:
        if dcf is not None:
            net.add_node(NODE, str(dcf))
        yield net
    finally:
        net.disconnect()


def download(node: canopen.RemoteNode) -> int:
    """CiA 306 DCF download with plain canopen: each writable entry that has a value, in order."""
    written = 0
    for key, var in sorted(variables(node.object_dictionary).items()):
        if var.writable and var.value is not None:
            entry = (
                node.sdo[key[0]]
                if isinstance(node.object_dictionary[key[0]], canopen.objectdictionary.ODVariable)
                else node.sdo[key[0]][key[1]]
            )
            entry.raw = var.value
            written += 1
    return written


def state(imu: EmulatedImu) -> dict:
    s = imu.store
    return {
        "active": s.active_value(), "stored": s.stored_value(), "activations": s.activation_count,
        "ids": {a: s.active_id(a) for a in AXES}, "refusal": s.last_refusal,
        "banks": {k: (b.content, b.crc, s.check(*k).status) for k, b in s.banks.items()},
        "file": imu.config.state_path.read_text().replace(f'"serial": {SERIAL}', ""),  # type: ignore[union-attr]
    }  # fmt: skip


def test_plain_canopen_download_of_the_dcf_equals_canical_push(tmp_path: Path) -> None:
    sets = imu_sets()
    dcf, done = export(tmp_path, sets)
    assert done.returncode == 0, done.stderr
    with emulated(tmp_path, "by-dcf.json") as (imu, channel), writer(channel, dcf) as net:
        node = net[NODE]
        assert download(node) == 2 * len(AXES) + 1  # content and CRC per axis, then the selector
        node.sdo["Store parameters"]["Save all parameters"].raw = STORE_SIGNATURE
        by_dcf = state(imu)
    with emulated(tmp_path, "by-push.json") as (imu, channel), writer(channel) as net:
        push_sets(ImuClient(net, NODE, 1.0), {a: (f"{a}.yaml", c) for a, c in sets.items()})
        by_push = state(imu)
    assert by_dcf["ids"] == {a: encode_set(c)[1] for a, c in sets.items()}
    assert by_dcf == by_push


def test_device_refuses_a_dcf_for_the_bank_it_runs(tmp_path: Path) -> None:
    """A DCF cannot pick the inactive bank: one naming the running bank stops at the first write
    and the device keeps running its sets."""
    dcf, _ = export(tmp_path, imu_sets(1))
    with emulated(tmp_path, "dev.json") as (imu, channel):
        with writer(channel) as net:
            push_sets(ImuClient(net, NODE, 1.0), {a: (a, c) for a, c in imu_sets().items()})  # runs bank A
        before = state(imu)
        with writer(channel, dcf) as net, pytest.raises(SdoAbortedError):
            download(net[NODE])
        assert state(imu)["ids"] == before["ids"] and "is active" in imu.store.last_refusal


def test_export_with_a_channel_checks_the_sets_against_the_node(tmp_path: Path, capsys) -> None:
    """--channel: the node is asked as push asks it; its serial and rated range are the checks."""
    from dataclasses import replace

    from canical.commands.cli import main

    paths = []
    for axis in AXES:
        paths.append(str(tmp_path / f"imu-{axis}.yaml"))
        coefficient_file.save(paths[-1], imu_set(axis))
    other = tmp_path / "other-z.yaml"
    coefficient_file.save(other, replace(imu_set("z"), sensor_id=str(int(imu_set("z").sensor_id) + 1)))
    with emulated(tmp_path, "state.json") as (_imu, channel):
        bus = ["--node", str(NODE), "--interface", "virtual", "--channel", channel, "--timeout", "2"]
        out = tmp_path / "imu.dcf"
        assert main(["export", "dcf", *paths, "-o", str(out), *bus]) == 0
        printed = capsys.readouterr().out
        assert out.exists() and "offline" not in printed
        out.unlink()
        assert main(["export", "dcf", str(other), "-o", str(out), *bus]) == 2
        err = capsys.readouterr().err.strip()
        assert f"this device is serial {SERIAL}" in err and "\n" not in err and not out.exists()


def test_a_dcf_of_signed_sets_carries_their_signatures_and_a_provisioned_device_takes_it(
        tmp_path: Path) -> None:
    """Each bank's Signature follows its Content and CRC32 (sub-index order, so the Content write
    does not clear it); a device with a trust key activates the signed DCF and refuses the same
    sets unsigned, keeping the sets it ran."""
    from support.signed_banks import LAB_PUBLIC, LAB_SEED

    from canical.sets.signed_file import sign_file

    sets = imu_sets()
    signed = tmp_path / "signed"
    signed.mkdir()
    paths = []
    for axis, cset in sets.items():
        paths.append(signed / f"imu-{axis}.yaml")
        coefficient_file.save(paths[-1], cset)
        sign_file(paths[-1], LAB_SEED, 2)
    dcf = tmp_path / "signed.dcf"
    command = [sys.executable, "-m", "canical", "export", "dcf", *map(str, paths), "-o", str(dcf)]
    done = subprocess.run(command, capture_output=True, text=True, check=False)
    assert done.returncode == 0 and "signed: x, y, z" in done.stdout, done.stderr
    o = imu_objects()
    od = canopen.import_od(str(dcf), NODE)
    for axis in AXES:
        ref = o.bank(axis, "A")
        assert len(od[ref.index][ref.signature].value) == 80
    unsigned, _ = export(tmp_path, sets, name="unsigned.dcf")
    with emulated(tmp_path, "trusting.json") as (imu, channel):
        imu.store.write_trust_key(LAB_PUBLIC)
        with writer(channel, unsigned) as net, pytest.raises(SdoAbortedError):
            download(net[NODE])
        assert imu.store.active_value() == 0 and "not signed" in imu.store.last_refusal
        with writer(channel, dcf) as net:
            assert download(net[NODE]) == 3 * len(AXES) + 1  # content, CRC, signature; the selector
        assert {a: imu.store.active_id(a) for a in AXES} == {a: encode_set(c)[1] for a, c in sets.items()}
        assert imu.store.trust.counter == 2


def test_an_imu_sets_signature_goes_to_its_coupling_bank_in_the_dcf() -> None:
    from support.imu_fixtures import imu_triad_set

    from canical.device.bank_payload import encode_coupling
    from canical.device.dcf_export import bank_values, section_name

    imu = imu_triad_set(0)
    o = imu_objects()
    signature = bytes(range(80))
    values = bank_values(o, {c.axis: c for c in imu.axes}, "B", encode_coupling(imu), {"imu": signature})
    ref = o.coupling_bank("B")
    assert values[section_name(ref.index, ref.signature)] == signature.hex().upper()
    assert not any(section_name(o.bank(a, "B").index, o.bank(a, "B").signature) in values for a in AXES)
