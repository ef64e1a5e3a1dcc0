"""The device checks signatures (BankStore, as the emulated IMU runs it): once a trust key is
provisioned, a bank is activated only with a valid signature by that key, for this device's
sensor, of a version not below the anti-rollback counter; every other case is refused with one
line and the previous set stays active. Key, provisioning state and counter survive a power
cycle; an old state file without them loads as a device never provisioned."""

from __future__ import annotations

import json
from pathlib import Path

import pytest
from support.imu_fixtures import SERIAL, imu_set, imu_triad_set
from support.signed_banks import (
    COUNTER,
    LAB_PUBLIC,
    LAB_SEED,
    VERSION,
    axis_cases,
    bank_signature,
    crc,
    imu_cases,
    imu_signature,
)

from canical.device.bank_payload import encode_set
from canical.device.coefficient_banks import BankRefusal, BankStore
from canical.frames.imu_dictionary import (
    ABORT_DEVICE_STATE,
    ABORT_REFUSED,
    ABORT_VALUE_RANGE,
    AXES,
    PROVISION_CLOSE_SIGNATURE,
    pack_active,
)
from canical.sets.admission import DeviceLimits
from canical.sets.signing import public_of

LIMITS = DeviceLimits(SERIAL, dict.fromkeys(AXES, 50.0))


def write_axis(store: BankStore, axis: str, bank: str, content: bytes, crc_: int, signature: bytes) -> None:
    store.write_content(axis, bank, content)
    store.write_crc(axis, bank, crc_)
    if signature:
        store.write_signature(axis, bank, signature)


def provisioned(state: Path | None = None) -> BankStore:
    """A device with the lab's key, running a signed z set of version COUNTER in bank A."""
    store = BankStore(LIMITS, 16384, state)
    store.write_trust_key(LAB_PUBLIC)
    content, crc_ = encode_set(imu_set("z", family=1))
    write_axis(store, "z", "A", content, crc_, bank_signature(LAB_SEED, content, COUNTER))
    store.activate(pack_active({"z": "A"}))
    assert store.trust.counter == COUNTER
    return store


@pytest.mark.parametrize("case", axis_cases(imu_set("z")), ids=lambda c: c.name)
def test_every_axis_case_is_refused_in_one_line_but_the_valid_one(case) -> None:
    store = provisioned()
    before = store.active_id("z")
    write_axis(store, "z", "B", case.content, case.crc, case.signature)
    if case.refusal is None:
        store.activate(pack_active({"z": "B"}))
        assert store.active_id("z") == case.crc and store.trust.counter == VERSION
        return
    with pytest.raises(BankRefusal) as refused:
        store.activate(pack_active({"z": "B"}))
    assert refused.value.code == ABORT_REFUSED and case.refusal in refused.value.reason
    assert "\n" not in refused.value.reason and store.last_refusal == refused.value.reason
    assert store.active_id("z") == before and store.active["z"] == "A" and store.trust.counter == COUNTER


def write_imu(store: BankStore, case, bank: str) -> None:
    for axis, content in zip(AXES, case.axes, strict=True):
        write_axis(store, axis, bank, content, crc(content), b"")
    store.write_coupling_content(bank, case.coupling)
    store.write_coupling_crc(bank, case.coupling_crc)
    store.write_imu_set_id(bank, case.imu_set_id)
    if case.signature:
        store.write_coupling_signature(bank, case.signature)


@pytest.mark.parametrize("case", imu_cases(imu_triad_set(0)), ids=lambda c: c.name)
def test_every_imu_set_case_is_refused_in_one_line_but_the_valid_one(case) -> None:
    """The coupling bank carries the IMU set's signature; it covers the three axes too."""
    store = BankStore(LIMITS, 16384)
    store.write_trust_key(LAB_PUBLIC)
    old = imu_triad_set(1)
    write_imu(store, imu_cases(old)[-1], "A")
    store.write_coupling_signature("A", imu_signature(LAB_SEED, old, COUNTER))
    store.activate(pack_active(dict.fromkeys(AXES, "A"), "A"))
    before = store.active_imu_set()
    write_imu(store, case, "B")
    selector = pack_active(dict.fromkeys(AXES, "B"), "B")
    if case.refusal is None:
        store.activate(selector)
        assert store.active_imu_set() == imu_triad_set(0) and store.trust.counter == VERSION
        return
    with pytest.raises(BankRefusal) as refused:
        store.activate(selector)
    assert case.refusal in refused.value.reason and "\n" not in refused.value.reason
    assert store.active_imu_set() == before and store.trust.counter == COUNTER


def test_single_axis_banks_under_no_key_activate_as_before() -> None:
    store = BankStore(LIMITS, 16384)
    content, crc_ = encode_set(imu_set("x"))
    write_axis(store, "x", "A", content, crc_, b"")
    store.activate(pack_active({"x": "A"}))
    assert store.active_id("x") == crc_ and store.trust.counter == 0


def test_a_content_write_clears_the_banks_signature() -> None:
    store = provisioned()
    content, crc_ = encode_set(imu_set("z"))
    write_axis(store, "z", "B", content, crc_, bank_signature(LAB_SEED, content, VERSION))
    store.write_content("z", "B", content)  # rewritten: the signature must follow again
    with pytest.raises(BankRefusal, match="not signed"):
        store.activate(pack_active({"z": "B"}))


def test_the_key_is_written_only_while_provisioning_is_open() -> None:
    store = BankStore(LIMITS, 16384)
    with pytest.raises(BankRefusal, match="no trust key") as refused:
        store.close_provisioning(PROVISION_CLOSE_SIGNATURE)
    assert refused.value.code == ABORT_DEVICE_STATE
    with pytest.raises(BankRefusal, match="not 32") as refused:
        store.write_trust_key(b"\x01" * 31)
    assert refused.value.code == ABORT_VALUE_RANGE
    store.write_trust_key(public_of(bytes(32)))
    store.write_trust_key(LAB_PUBLIC)  # replaced while open
    with pytest.raises(BankRefusal, match="'lock'"):
        store.close_provisioning(1)
    store.close_provisioning(PROVISION_CLOSE_SIGNATURE)
    with pytest.raises(BankRefusal, match="provisioning is closed") as refused:
        store.write_trust_key(public_of(bytes(32)))
    assert refused.value.code == ABORT_DEVICE_STATE and store.trust.key == LAB_PUBLIC


def test_key_provisioning_and_counter_survive_a_power_cycle(tmp_path: Path) -> None:
    state = tmp_path / "imu.json"
    store = provisioned(state)
    store.close_provisioning(PROVISION_CLOSE_SIGNATURE)
    # persisted at once, not at the next store: a power cycle without one keeps them
    again = BankStore.boot(LIMITS, 16384, state)
    trust = again.trust
    assert (trust.key, trust.provisioning_open, trust.counter) == (LAB_PUBLIC, False, COUNTER)
    assert again.active["z"] is None  # the banks were never stored
    store.store(True)
    again = BankStore.boot(LIMITS, 16384, state)
    assert again.active["z"] == "A" and again.trust.counter == COUNTER
    with pytest.raises(BankRefusal, match="provisioning is closed"):
        again.write_trust_key(public_of(bytes(32)))
    store.restore_defaults(True)  # the sets go; the trust stays
    again = BankStore.boot(LIMITS, 16384, state)
    assert again.active["z"] is None and again.trust.key == LAB_PUBLIC and not again.trust.provisioning_open
    content, crc_ = encode_set(imu_set("z"))
    write_axis(again, "z", "B", content, crc_, bank_signature(LAB_SEED, content, COUNTER - 1))
    with pytest.raises(BankRefusal, match="a rollback"):
        again.activate(pack_active({"z": "B"}))


def test_damaged_banks_in_the_state_file_keep_the_trust(tmp_path: Path) -> None:
    state = tmp_path / "imu.json"
    store = provisioned(state)
    store.close_provisioning(PROVISION_CLOSE_SIGNATURE)
    store.store(True)
    damaged = json.loads(state.read_text())
    damaged["banks"] = "garbage"
    state.write_text(json.dumps(damaged))
    again = BankStore.boot(LIMITS, 16384, state)
    assert again.active["z"] is None
    trust = again.trust
    assert (trust.key, trust.provisioning_open, trust.counter) == (LAB_PUBLIC, False, COUNTER)


@pytest.mark.parametrize("damage", ["trust section", "whole file"])
def test_a_damaged_trust_fails_closed(tmp_path: Path, damage: str) -> None:
    """Damage to the stored trust must not reopen provisioning (anyone able to damage the file could
    then install their own key): the device boots refusing every activation and every key."""
    state = tmp_path / "imu.json"
    store = provisioned(state)
    store.close_provisioning(PROVISION_CLOSE_SIGNATURE)
    store.store(True)
    if damage == "trust section":
        content = json.loads(state.read_text())
        content["trust"]["key"] = "not base64 !"
        state.write_text(json.dumps(content))
    else:
        state.write_text(state.read_text()[:40])
    again = BankStore.boot(LIMITS, 16384, state)
    assert not again.trust.provisioning_open and again.trust.key == b""
    with pytest.raises(BankRefusal, match="provisioning is closed"):
        again.write_trust_key(public_of(bytes(32)))
    content, crc_ = encode_set(imu_set("z"))
    write_axis(again, "z", "B", content, crc_, bank_signature(LAB_SEED, content, COUNTER + 1))
    with pytest.raises(BankRefusal, match="stored trust is damaged"):
        again.activate(pack_active({"z": "B"}))


def test_an_old_state_file_without_trust_loads_unprovisioned(tmp_path: Path) -> None:
    state = tmp_path / "imu.json"
    store = BankStore(LIMITS, 16384, state)
    content, crc_ = encode_set(imu_set("x"))
    write_axis(store, "x", "A", content, crc_, b"")
    store.activate(pack_active({"x": "A"}))
    store.store(True)
    old = json.loads(state.read_text())
    del old["trust"]
    for entry in old["banks"].values():
        del entry["signature"]
    state.write_text(json.dumps(old))
    again = BankStore.boot(LIMITS, 16384, state)
    assert again.active_id("x") == crc_ and again.trust.key == b"" and again.trust.provisioning_open
