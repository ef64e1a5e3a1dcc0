"""The IMU's object dictionary and bank rules, without a bus.

What the device promises (a running set is never touched by a download; activation
switches every axis at once or none; a refused write changes nothing; a power cycle
brings back exactly what was stored, re-checked) is asserted here on the bank store
itself, including under random sequences of writes; the same rules over real CANopen
SDO on vcan are in ``test_imu_canopen_vcan.py``.
"""

from __future__ import annotations

import json
import os
import zlib
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canical.bus.active_sets import AxisSet, build
from canical.device.bank_payload import decode_set, encode_set
from canical.device.coefficient_banks import LOCK_LEASE_S, BankRefusal, BankStore
from canical.device.sdo_download import plan_push
from canical.errors import CanicalError
from canical.frames.imu_dictionary import (
    ABORT_DEVICE_STATE,
    ABORT_REFUSED,
    ABORT_VALUE_RANGE,
    AXES,
    STATUS_CRC_MISMATCH,
    STATUS_EMPTY,
    STATUS_REFUSED,
    STATUS_VALID,
    eds_path,
    imu_objects,
    object_dictionary,
    pack_active,
    unpack_active,
)
from canical.frames.imu_frames import ImuFrames, load_database, set_tag
from canical.sets.admission import DeviceLimits, admission_problem
from canical.sets.coefficient_file import canonical_bytes, set_crc

try:
    from support.imu_fixtures import SERIAL, imu_set, imu_sets
except ImportError:  # pragma: no cover
    from tests.imu_fixtures import SERIAL, imu_set, imu_sets  # type: ignore[no-redef]

ROOT = Path(__file__).resolve().parents[2]
LIMITS = DeviceLimits(SERIAL, dict.fromkeys(AXES, 50.0))


# --------------------------------------------------------------------------------------------
# The object dictionary and the frames
# --------------------------------------------------------------------------------------------


def test_eds_in_services_is_the_packaged_one() -> None:
    """services/ deploys the very file the code reads (a link, so they cannot drift)."""
    deployed = ROOT / "services" / "canical-imu.eds"
    assert deployed.resolve() == eds_path().resolve()
    assert (ROOT / "canical" / "data" / "canical.dbc").resolve() == (ROOT / "dbc" / "canical.dbc").resolve()


def test_object_dictionary_has_every_object_the_tools_use() -> None:
    od = object_dictionary(0x22)
    o = imu_objects()
    assert o.serial == (0x1018, 4) and o.store == (0x1010, 1) and o.restore == (0x1011, 1)
    keys = [o.capacity, o.active_banks, o.activation_count, o.last_refusal, o.download_lock,
            o.correction_mode, o.stored_state, *o.rated_range.values(), *o.active_set_id.values()]
    for b in o.banks.values():
        keys += [(b.index, b.content), (b.index, b.crc), (b.index, b.status), (b.index, b.size)]
    assert len(set(keys)) == len(keys)
    for index, sub in keys:
        obj = od[index]
        assert sub == 0 or sub in obj
    assert len({b.index for b in o.banks.values()}) == 6
    assert od[0x1800][1].default == 0x180 + 0x22  # COB-IDs follow the node id


def test_tpdo_mappings_match_the_dbc_layout() -> None:
    """Each TPDO's mapped objects sit exactly where the DBC puts the signals they carry."""
    db = load_database()
    od = object_dictionary(0x10)
    for tpdo, name in enumerate(("IMU_RAW", "IMU_AUX", "IMU_RATE")):
        msg = db.get_message_by_name(name)
        assert msg.frame_id == od[0x1800 + tpdo][1].default  # the DBC describes node 0x10
        mapping = od[0x1A00 + tpdo]
        bit = 0
        starts = {}
        for sub in range(1, mapping[0].default + 1):
            entry = mapping[sub].default
            index, subindex, length = entry >> 16, (entry >> 8) & 0xFF, entry & 0xFF
            obj = od[index] if subindex == 0 and not hasattr(od[index], "subindices") else od[index][subindex]
            assert len(obj) == length, (name, obj.name)
            starts[bit] = length
            bit += length
        assert bit <= 8 * msg.length
        for sig in msg.signals:  # every signal lies inside one mapped object
            owner = max(s for s in starts if s <= sig.start)
            assert sig.start + sig.length <= owner + starts[owner], (name, sig.name)


def test_frames_move_with_the_node_id() -> None:
    f = ImuFrames(0x22)
    assert f.ids == {"IMU_RAW": 0x1A2, "IMU_AUX": 0x2A2, "IMU_RATE": 0x3A2, "TABLE_REF": 0x120}
    fid, data = f.raw((100, -200, 32767), 37.4, 21)
    values = f.decode(fid, data).values  # type: ignore[union-attr]
    assert (values["GyroRawX"], values["GyroRawY"], values["GyroRawZ"]) == (100, -200, 32767)
    assert values["Temperature"] == pytest.approx(37.4) and values["Counter"] == 21 % 16
    with pytest.raises(CanicalError, match="node id 200"):
        ImuFrames(200)


@given(st.integers(0, 0xFFFFFFFF), st.integers(0, 0xFFFFFFFF), st.integers(0, 0xFFFFFFFF))
def test_device_set_tag_is_the_daemons(x: int, y: int, z: int) -> None:
    """IMU_RATE and CANICAL_RATE carry the same tag for the same sets."""
    axes = tuple(AxisSet(a, f"GyroRaw{a.upper()}", set_id=i) for a, i in zip(AXES, (x, y, z), strict=True))
    assert set_tag({"x": x, "y": y, "z": z}) == build(axes).tag


@given(st.lists(st.sampled_from([None, "A", "B"]), min_size=3, max_size=3))
def test_selector_packs_and_unpacks(banks: list) -> None:
    selection = dict(zip(AXES, banks, strict=True))
    assert unpack_active(pack_active(selection)) == selection


@pytest.mark.parametrize("value", [0x03, 0x0C, 0x30, 0xC0, 0xFF, 0x100])
def test_selector_rejects_codes_naming_no_bank(value: int) -> None:
    with pytest.raises(ValueError):
        unpack_active(value)


# --------------------------------------------------------------------------------------------
# Bank payload and admission
# --------------------------------------------------------------------------------------------


def test_bank_payload_round_trip_and_crc_is_the_set_id() -> None:
    cset = imu_set("z")
    content, crc = encode_set(cset)
    assert crc == set_crc(cset) and content == canonical_bytes(cset.to_dict())
    assert decode_set(content, crc, "bank") == cset


def test_bank_payload_refuses_damage_and_non_canonical_json() -> None:
    content, crc = encode_set(imu_set("z"))
    with pytest.raises(CanicalError, match="CRC mismatch"):
        decode_set(content[:-1] + b" ", crc, "bank Z A")
    loose = json.dumps(json.loads(content), indent=1).encode()
    with pytest.raises(CanicalError, match="canonical"):
        decode_set(loose, zlib.crc32(loose), "bank Z A")


def test_admission_refuses_other_sensor_axis_and_narrow_span() -> None:
    z = imu_set("z")
    assert admission_problem(z, "z", LIMITS) is None
    assert "serial 4712" in (admission_problem(z, "z", DeviceLimits(4712, LIMITS.rated_range_dps)) or "")
    assert "axis z, not axis x" in (admission_problem(z, "x", LIMITS) or "")
    wide = DeviceLimits(SERIAL, dict.fromkeys(AXES, 75.0))
    assert "does not cover the rated range ±75" in (admission_problem(z, "z", wide) or "")


def test_plan_writes_the_inactive_bank_and_refuses_before_writing() -> None:
    sets = {a: (f"{a}.yaml", c) for a, c in imu_sets().items()}
    active = {"x": "A", "y": None, "z": "B"}
    ids = {"x": set_crc(imu_set("x")), "y": 0, "z": 0x1234}
    plan = plan_push(sets, LIMITS, active, ids, 0x10)
    assert [(p.axis, p.bank, p.unchanged) for p in plan.axes] == [
        ("x", "B", True), ("y", "A", False), ("z", "A", False)]
    assert unpack_active(plan.selector_after) == {"x": "A", "y": "A", "z": "A"}
    with pytest.raises(CanicalError, match=r"z\.yaml: not for this device .*serial 4712"):
        plan_push({"z": sets["z"]}, DeviceLimits(4712, LIMITS.rated_range_dps), active, ids, 0x10)


# --------------------------------------------------------------------------------------------
# The bank store: the device's rules
# --------------------------------------------------------------------------------------------


def loaded(store: BankStore, axis: str, bank: str, cset=None, crc: int | None = None) -> None:
    content, good = encode_set(cset or imu_set(axis))
    store.write_content(axis, bank, content)
    store.write_crc(axis, bank, good if crc is None else crc)


def test_activation_switches_all_axes_or_none(tmp_path: Path) -> None:
    store = BankStore(LIMITS, 16384, tmp_path / "s.json")
    for axis in AXES:
        loaded(store, axis, "A")
    loaded(store, "z", "B", crc=0xDEADBEEF)  # a damaged bank for z
    store.activate(pack_active({"x": "A", "y": "A", "z": "A"}))
    before = store.active_value()
    with pytest.raises(BankRefusal) as refused:
        store.activate(pack_active({"x": "A", "y": "A", "z": "B"}))
    assert refused.value.code == ABORT_REFUSED and "CRC mismatch" in store.last_refusal
    assert store.active_value() == before and store.activation_count == 1


def test_active_bank_cannot_be_written_or_dropped() -> None:
    store = BankStore(LIMITS, 16384)
    loaded(store, "z", "A")
    store.activate(pack_active({"z": "A"}))
    for write in (lambda: store.write_content("z", "A", b"{}"), lambda: store.write_crc("z", "A", 1)):
        with pytest.raises(BankRefusal) as refused:
            write()
        assert refused.value.code == ABORT_DEVICE_STATE
    with pytest.raises(BankRefusal) as refused:
        store.activate(pack_active({}))
    assert refused.value.code == ABORT_VALUE_RANGE
    assert store.active_id("z") == set_crc(imu_set("z"))


@pytest.mark.parametrize(("make", "status", "reason"), [
    (lambda s: None, STATUS_EMPTY, "empty"),
    (lambda s: loaded(s, "z", "B", crc=7), STATUS_CRC_MISMATCH, "CRC mismatch"),
    (lambda s: loaded(s, "z", "B", cset=imu_set("z", sensor="4712")), STATUS_REFUSED, "serial 4711"),
    (lambda s: loaded(s, "z", "B", cset=imu_set("x")), STATUS_REFUSED, "axis x, not axis z"),
])
def test_invalid_banks_are_reported_and_refused(make, status: int, reason: str) -> None:
    store = BankStore(LIMITS, 16384)
    make(store)
    assert store.check("z", "B").status == status
    with pytest.raises(BankRefusal):
        store.activate(pack_active({"z": "B"}))
    assert reason in store.last_refusal and store.active_value() == 0


def test_power_cycle_brings_back_what_was_stored(tmp_path: Path) -> None:
    state = tmp_path / "imu.json"
    store = BankStore.boot(LIMITS, 16384, state)
    loaded(store, "z", "A")
    store.activate(pack_active({"z": "A"}))
    store.store(True)
    loaded(store, "z", "B", cset=imu_set("z", family=1))
    store.activate(pack_active({"z": "B"}))  # activated, not stored
    again = BankStore.boot(LIMITS, 16384, state)
    assert again.active == {"x": None, "y": None, "z": "A"}
    assert again.active_id("z") == set_crc(imu_set("z"))
    again.restore_defaults(True)
    assert BankStore.boot(LIMITS, 16384, state).active_value() == 0


def test_boot_drops_a_damaged_active_bank(tmp_path: Path, caplog: pytest.LogCaptureFixture) -> None:
    state = tmp_path / "imu.json"
    store = BankStore.boot(LIMITS, 16384, state)
    loaded(store, "z", "A")
    loaded(store, "x", "A")
    store.activate(pack_active({"x": "A", "z": "A"}))
    store.store(True)
    content = json.loads(state.read_text())
    content["banks"]["z.A"]["crc"] ^= 1  # NVM corruption of one bank
    state.write_text(json.dumps(content))
    again = BankStore.boot(LIMITS, 16384, state)
    assert again.active == {"x": "A", "y": None, "z": None}
    assert "axis z left without a set" in caplog.text
    state.write_text("{not json")
    assert BankStore.boot(LIMITS, 16384, state).active_value() == 0


def test_store_is_atomic_a_failed_write_keeps_the_old_file(tmp_path: Path, monkeypatch) -> None:
    state = tmp_path / "imu.json"
    store = BankStore.boot(LIMITS, 16384, state)
    loaded(store, "z", "A")
    store.activate(pack_active({"z": "A"}))
    store.store(True)
    old = state.read_bytes()
    loaded(store, "z", "B", cset=imu_set("z", family=1))
    store.activate(pack_active({"z": "B"}))

    def dies(*_a, **_k):
        raise OSError("power lost")

    monkeypatch.setattr(os, "replace", dies)
    with pytest.raises(OSError):
        store.store(True)
    assert state.read_bytes() == old and not list(tmp_path.glob(".imu.json.*"))


def test_download_lock_is_exclusive_and_expires() -> None:
    now = [0.0]
    store = BankStore(LIMITS, 16384, clock=lambda: now[0])
    store.take_lock(0x1111)
    with pytest.raises(BankRefusal) as refused:
        store.take_lock(0x2222)
    assert refused.value.code == ABORT_DEVICE_STATE and "another download" in store.last_refusal
    store.take_lock(0x1111)  # the holder renews
    now[0] += LOCK_LEASE_S + 0.1
    store.take_lock(0x2222)  # a dead holder's lock expires
    store.take_lock(0)
    assert store.current_lock() == 0


OPS = st.lists(
    st.one_of(
        st.tuples(st.just("write"), st.sampled_from(AXES), st.sampled_from("AB"),
                  st.sampled_from(["good", "other", "bad-crc", "foreign", "wrong-axis", "garbage"])),
        st.tuples(st.just("activate"), st.integers(0, 0x3F)),
        st.tuples(st.just("store")),
        st.tuples(st.just("reboot")),
    ),
    max_size=30,
)


@settings(max_examples=60, deadline=None)
@given(OPS)
def test_random_operations_never_leave_an_invalid_set_active(tmp_path_factory, ops) -> None:
    """Whatever is written in whatever order, every active bank is a valid set for its axis,
    a refused operation changes nothing that runs, and a reboot runs what was last stored."""
    state = tmp_path_factory.mktemp("imu") / "imu.json"
    store = BankStore.boot(LIMITS, 16384, state)
    stored = store.active_value()
    for op in ops:
        running = {a: store.active_id(a) for a in AXES}
        try:
            if op[0] == "write":
                _, axis, bank, kind = op
                cset = {"good": imu_set(axis), "other": imu_set(axis, family=1),
                        "foreign": imu_set(axis, sensor="999"),
                        "wrong-axis": imu_set("y" if axis != "y" else "x")}.get(kind)
                content, crc = encode_set(cset) if cset else (b'{"schema":1}', 5)
                store.write_content(axis, bank, content)
                store.write_crc(axis, bank, crc ^ (1 if kind == "bad-crc" else 0))
            elif op[0] == "activate":
                store.activate(op[1])
            elif op[0] == "store":
                store.store(True)
                stored = store.active_value()
            else:
                store = BankStore.boot(LIMITS, 16384, state)
                assert store.active_value() == stored
        except BankRefusal:
            assert {a: store.active_id(a) for a in AXES} == running
        for axis, bank in store.active.items():
            if bank is not None:
                check = store.check(axis, bank)
                assert check.status == STATUS_VALID and check.cset is not None and check.cset.axis == axis


def test_daemon_config_device_key_is_checked(tmp_path: Path) -> None:
    from canical.bus.daemon_config import load_config

    try:
        from support.daemon_fixtures import write_config
    except ImportError:  # pragma: no cover
        from tests.daemon_fixtures import write_config  # type: ignore[no-redef]

    config = load_config(write_config(tmp_path, "vcan0", device={"node": 0x10}))
    assert config.device is not None and (config.device.node, config.device.timeout_s) == (0x10, 1.0)
    assert load_config(write_config(tmp_path, "vcan0")).device is None
    with pytest.raises(CanicalError, match=r"device\.node: must be a CANopen node id 1\.\.127, got 200"):
        load_config(write_config(tmp_path, "vcan0", device={"node": 200}))
    with pytest.raises(CanicalError, match=r"device\.bank: unknown key"):
        load_config(write_config(tmp_path, "vcan0", device={"node": 1, "bank": "A"}))


def test_emulator_switches_on_each_undeclared_effect():
    """`canical emulate` options give the simulated IMU the effects the calibrator must find."""
    import argparse

    from canical.commands import emulate
    from canical.sim import effects as fx

    parser = argparse.ArgumentParser()
    emulate.register(parser.add_subparsers())
    args = parser.parse_args(["emulate", "--channel", "x", "--temp-bias", "0.01", "--temp-scale", "2e-4",
                              "--warmup", "0.3", "--warmup-tau", "120", "--supply-bias", "0.2",
                              "--direction-offset", "0.05"])
    kinds = {type(e): e for e in emulate.undeclared_effects(args)}
    assert set(kinds) == {fx.TemperatureEffect, fx.WarmupEffect, fx.SupplyEffect, fx.DirectionEffect}
    assert kinds[fx.TemperatureEffect].scale_per_c == 2e-4 and kinds[fx.WarmupEffect].tau_s == 120
    config = emulate.stream_config(args)
    assert all(len(g.effects) == 4 for g in config.gyros.values())
    none = parser.parse_args(["emulate", "--channel", "x"])
    assert emulate.undeclared_effects(none) == ()
