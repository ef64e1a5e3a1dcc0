"""Signed sets over CANopen SDO, against the emulated IMU in-process on python-can's virtual bus:
the key provisioned once, every refusal case an SDO abort with the device's one-line reason and
the previous set kept, `canical push` writing the signature of a signed set file (an axis set's
on its bank, an IMU set's on its coupling bank), a push interrupted between the payload and the
activation, and the trust surviving a power cycle."""

from __future__ import annotations

from pathlib import Path

import pytest
from support.imu_fixtures import imu_set, imu_triad_set
from support.signed_banks import (
    COUNTER,
    LAB_PUBLIC,
    LAB_SEED,
    STRANGER_SEED,
    axis_cases,
    bank_signature,
    crc,
    imu_cases,
)
from test_imu_set_device import bus, client, cut_off, emulated, one_line

from canical.commands.cli import main
from canical.device.bank_payload import encode_set
from canical.device.sdo_download import DeviceSilent, ImuClient, push_sets
from canical.errors import CanicalError
from canical.files.key_file import write_key_pair
from canical.frames.imu_dictionary import AXES, PROVISION_CLOSE_SIGNATURE, imu_objects, pack_active
from canical.sets import coefficient_file
from canical.sets import imu_set as imu_file
from canical.sets.signed_file import read_set_file, sign_file
from canical.sets.signing import public_of


def provision(c: ImuClient, *, close: bool = True) -> None:
    o = c.objects
    c.download(o.trust_key, LAB_PUBLIC, "writing the trust key")
    if close:
        c.write_uint(o.provisioning, PROVISION_CLOSE_SIGNATURE, 4, "closing provisioning")


def write_bank(c: ImuClient, axis: str, bank: str, content: bytes, crc_: int, signature: bytes) -> None:
    ref = c.objects.bank(axis, bank)
    c.download((ref.index, ref.content), content, "content")
    c.write_uint((ref.index, ref.crc), crc_, 4, "crc")
    if signature:
        c.download((ref.index, ref.signature), signature, "signature")


def previous_z(c: ImuClient) -> int:
    """A signed z set of version COUNTER activated in bank A; its id."""
    content, crc_ = encode_set(imu_set("z", family=1))
    write_bank(c, "z", "A", content, crc_, bank_signature(LAB_SEED, content, COUNTER))
    c.write_uint(c.objects.active_banks, pack_active({"z": "A"}), 1, "activating")
    return crc_


def test_every_axis_case_over_sdo(tmp_path: Path) -> None:
    with emulated(tmp_path) as (dev, channel), client(channel) as c:
        provision(c)
        for case in axis_cases(imu_set("z")):
            before = previous_z(c) if c.active()["z"] != "A" else c.active_ids()["z"]
            write_bank(c, "z", "B", case.content, case.crc, case.signature)
            if case.refusal is None:
                c.write_uint(c.objects.active_banks, pack_active({"z": "B"}), 1, "activating")
                assert c.active_ids()["z"] == case.crc
                continue
            with pytest.raises(CanicalError) as refused:
                c.write_uint(c.objects.active_banks, pack_active({"z": "B"}), 1, "activating")
            assert case.refusal in str(refused.value) and "\n" not in str(refused.value), case.name
            assert c.active_ids()["z"] == before and dev.store.active["z"] == "A", case.name


def test_every_imu_set_case_over_sdo(tmp_path: Path) -> None:
    o = imu_objects()
    for k, case in enumerate(imu_cases(imu_triad_set(0))):
        with emulated(tmp_path, f"imu{k}.json") as (dev, channel), client(channel) as c:
            provision(c)
            old = imu_triad_set(1)
            previous = tmp_path / f"old{k}.yaml"
            imu_file.save(previous, old)
            sign_file(previous, LAB_SEED, COUNTER)
            push_sets(c, {}, imu=(str(previous), old), signatures=_signatures(previous))
            for axis, content in zip(AXES, case.axes, strict=True):
                write_bank(c, axis, "B", content, crc(content), b"")
            ref = o.coupling_bank("B")
            c.download((ref.index, ref.content), case.coupling, "coupling")
            c.write_uint((ref.index, ref.crc), case.coupling_crc, 4, "crc")
            c.write_uint((ref.index, ref.imu_set_id), case.imu_set_id, 4, "id")
            if case.signature:
                c.download((ref.index, ref.signature), case.signature, "signature")
            selector = pack_active(dict.fromkeys(AXES, "B"), "B")
            if case.refusal is None:
                c.write_uint(o.active_banks, selector, 1, "activating")
                assert dev.store.active_imu_set() == imu_triad_set(0)
                continue
            with pytest.raises(CanicalError) as refused:
                c.write_uint(o.active_banks, selector, 1, "activating")
            assert case.refusal in str(refused.value), case.name
            assert dev.store.active_imu_set() == old, case.name


def _signatures(path: Path) -> dict[str, bytes]:
    from canical.device.bank_signature import bank_signatures

    return bank_signatures([path])


def test_push_writes_the_signature_of_a_signed_file(tmp_path: Path, capsys) -> None:
    """`canical push` of signed files is activated; unsigned or stranger-signed ones are refused in
    one line and the device runs what it ran."""
    first, second = tmp_path / "z1.yaml", tmp_path / "z2.yaml"
    coefficient_file.save(first, imu_set("z"))
    coefficient_file.save(second, imu_set("z", family=1))
    with emulated(tmp_path) as (dev, channel):
        with client(channel) as c:
            provision(c)
        assert main(["push", str(first), *bus(channel)]) == 2  # unsigned
        assert "not signed" in one_line(capsys) and dev.store.active["z"] is None
        sign_file(first, STRANGER_SEED, 3)
        assert main(["push", str(first), *bus(channel)]) == 2
        assert "not by the device's trust key" in one_line(capsys)
        sign_file(first, LAB_SEED, 3)
        assert main(["push", str(first), *bus(channel)]) == 0
        assert "signed as version 3" in capsys.readouterr().out
        assert dev.store.active_id("z") == coefficient_file.set_crc(imu_set("z"))
        assert dev.store.trust.counter == 3
        sign_file(second, LAB_SEED, 2)  # an older version than the running one
        assert main(["push", str(second), *bus(channel)]) == 2
        assert "a rollback" in one_line(capsys)
        assert dev.store.active_id("z") == coefficient_file.set_crc(imu_set("z"))
    imu_path = tmp_path / "imu.yaml"
    imu_file.save(imu_path, imu_triad_set(0))
    sign_file(imu_path, LAB_SEED, 4)
    with emulated(tmp_path, "imu2.json") as (dev, channel):
        with client(channel) as c:
            provision(c)
        assert main(["push", str(imu_path), *bus(channel)]) == 0
        assert dev.store.active_imu_set() == imu_triad_set(0) and dev.store.trust.counter == 4


@pytest.mark.parametrize("stop_at", ["signature", "selector"])
def test_a_push_interrupted_between_payload_and_activation_keeps_the_old_set(tmp_path: Path,
                                                                            stop_at: str) -> None:
    o = imu_objects()
    path = tmp_path / "z.yaml"
    coefficient_file.save(path, imu_set("z"))
    sign_file(path, LAB_SEED, 9)
    with emulated(tmp_path) as (dev, channel), client(channel) as c:
        provision(c)
        before = previous_z(c)
        real_download, real_write = c.download, c.write_uint
        signature_at = (o.bank("z", "B").index, o.bank("z", "B").signature)
        cut_off(c, at_download=signature_at if stop_at == "signature" else None,
                at_selector=stop_at == "selector")
        with pytest.raises(DeviceSilent):
            push_sets(c, {"z": (str(path), imu_set("z"))}, signatures=_signatures(path))
        assert dev.store.active_id("z") == before and dev.store.trust.counter == COUNTER
        if stop_at == "signature":  # the payload without its signature is never activated
            c.download, c.write_uint = real_download, real_write  # type: ignore[method-assign]
            with pytest.raises(CanicalError, match="not signed"):
                c.write_uint(o.active_banks, pack_active({"z": "B"}), 1, "activating")
            assert dev.store.active_id("z") == before


def test_the_trust_survives_a_power_cycle_over_sdo(tmp_path: Path, capsys) -> None:
    o = imu_objects()
    with emulated(tmp_path) as (_, channel), client(channel) as c:
        assert c.read_uint(o.provisioning, "provisioning") == 1
        provision(c)
        previous_z(c)
    with emulated(tmp_path) as (dev, channel), client(channel) as c:
        assert c.read_uint(o.provisioning, "provisioning") == 0
        assert c.upload(o.trust_key, "key") == LAB_PUBLIC
        assert c.read_uint(o.rollback_counter, "counter") == COUNTER
        with pytest.raises(CanicalError, match="provisioning is closed"):
            c.download(o.trust_key, bytes(32), "writing the trust key")
        assert dev.store.trust.key == LAB_PUBLIC


def key_files(folder: Path) -> tuple[Path, Path]:
    """The lab's public key file and a stranger's."""
    folder.mkdir(exist_ok=True)
    _, lab = write_key_pair(folder / "lab", LAB_SEED, LAB_PUBLIC)
    _, stranger = write_key_pair(folder / "stranger", STRANGER_SEED, public_of(STRANGER_SEED))
    return lab, stranger


#: A device activates no bank whose CRC does not match; a rollback is the device's and the daemon's
#: check (a pull has no running version to compare with).
PULLED = [c for c in axis_cases(imu_set("z")) if c.name not in ("tampered, CRC kept", "rolled back")]


@pytest.mark.parametrize("case", PULLED, ids=lambda c: c.name)
def test_pull_trust_verifies_what_it_reads(tmp_path: Path, capsys, case) -> None:
    """A device without a trust key activates anything; `pull --trust` refuses, in one line and with
    exit 2, every set the lab did not sign for it, and writes the signed one with its signature."""
    lab, _ = key_files(tmp_path / "keys")
    out = tmp_path / "pulled.yaml"
    with emulated(tmp_path) as (_, channel):
        with client(channel) as c:
            write_bank(c, "z", "A", case.content, case.crc, case.signature)
            c.write_uint(c.objects.active_banks, pack_active({"z": "A"}), 1, "activating")
        code = main(["pull", *bus(channel), "--axis", "z", "-o", str(out), "--trust", str(lab)])
    if case.refusal is None:
        assert code == 0 and "trusted" in capsys.readouterr().out
        assert read_set_file(out).signed.record is not None
        assert main(["verify", str(out), "--trust", str(lab)]) == 0
        return
    line = one_line(capsys)
    assert code == 2 and not out.exists(), line
    expected = {"untrusted key": "not trusted", "garbage signature": "not trusted",
                "another sensor": "changed after signing", "unsigned": "not signed"}
    fallback = case.refusal if "bytes" in case.refusal else "changed after signing"
    assert expected.get(case.name, fallback) in line


def test_pull_of_a_signed_imu_set_gives_back_the_signed_file(tmp_path: Path, capsys) -> None:
    lab, stranger = key_files(tmp_path / "keys")
    path = tmp_path / "imu.yaml"
    imu_file.save(path, imu_triad_set(0))
    sign_file(path, LAB_SEED, 6)
    back = tmp_path / "back.yaml"
    with emulated(tmp_path) as (_, channel):
        with client(channel) as c:
            provision(c)
        assert main(["push", str(path), *bus(channel)]) == 0
        capsys.readouterr()
        assert main(["pull", *bus(channel), "--imu-set", "-o", str(back), "--trust", str(stranger)]) == 2
        assert "not trusted" in one_line(capsys) and not back.exists()
        assert main(["pull", *bus(channel), "--imu-set", "-o", str(back), "--trust", str(lab)]) == 0
    assert read_set_file(back).signed.record == read_set_file(path).signed.record
    assert imu_file.load(back) == imu_file.load(path) == imu_triad_set(0)


def test_provision_writes_the_key_once_and_closes(tmp_path: Path, capsys) -> None:
    lab, stranger = key_files(tmp_path / "keys")
    with emulated(tmp_path) as (dev, channel):
        assert main(["provision", "--key", str(lab), *bus(channel)]) == 0
        assert "provisioning open" in capsys.readouterr().out and dev.store.trust.provisioning_open
        # replaced while open, then closed
        assert main(["provision", "--key", str(stranger), *bus(channel), "--close"]) == 0
        assert "closed for good" in capsys.readouterr().out
        assert dev.store.trust.key == public_of(STRANGER_SEED)
        assert main(["provision", "--key", str(lab), *bus(channel), "--close"]) == 2
        assert "provisioning is closed with key" in one_line(capsys)
        assert dev.store.trust.key == public_of(STRANGER_SEED)
        # the same key again: said, not refused
        assert main(["provision", "--key", str(stranger), *bus(channel)]) == 0
        assert "trusts key" in capsys.readouterr().out
