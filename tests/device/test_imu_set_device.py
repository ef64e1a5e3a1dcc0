"""An IMU set on the device: coupling banks, one activation with the axes, push/pull/DCF.

The coupling travels with the three axes it was fitted on: the device keeps it in its own A/B
banks, activates it with the axes by the one selector write only when it belongs to them (they
make the IMU set its id names) and passes canical.sets.imu_set.check_coupling's rules, stores it
like the other banks, and applies it to its corrected rates. Push and pull run over real
CANopen SDO (canopen on python-can's virtual bus) against the emulated IMU in this process.
"""

from __future__ import annotations

import contextlib
import json
import uuid
import zlib
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import canopen
import numpy as np
import pytest
from support.imu_fixtures import SERIAL, imu_set, imu_triad_set

from canical.commands.cli import main
from canical.device.bank_payload import CouplingPayload, decode_coupling, encode_coupling, encode_set
from canical.device.coefficient_banks import BankRefusal, BankStore
from canical.device.emulated_imu import EmulatedImu, EmulatorConfig
from canical.device.sdo_download import DeviceSilent, ImuClient, pull_imu_set, push_sets
from canical.frames.imu_dictionary import (
    ABORT_DEVICE_STATE,
    ABORT_REFUSED,
    ABORT_VALUE_RANGE,
    AXES,
    STATUS_REFUSED,
    STATUS_VALID,
    imu_objects,
    object_dictionary,
    pack_active,
    unpack_active,
    unpack_coupling,
)
from canical.sets import imu_set as imu_file
from canical.sets.admission import DeviceLimits
from canical.sets.coefficient_file import canonical_bytes
from canical.sets.imu_corrector import ImuCorrector

LIMITS = DeviceLimits(SERIAL, dict.fromkeys(AXES, 50.0))
NODE = 0x10
SEEDS = (0, 1, 2)


def load(store: BankStore, imu, bank: str = "A", *, axes: bool = True,
         payload: CouplingPayload | None = None) -> CouplingPayload:
    """Write an IMU set's axes (bank ``bank`` of each) and its coupling (coupling bank ``bank``)."""
    if axes:
        for cset in imu.axes:
            content, crc = encode_set(cset)
            store.write_content(cset.axis, bank, content)
            store.write_crc(cset.axis, bank, crc)
    p = payload or encode_coupling(imu)
    store.write_coupling_content(bank, p.content)
    store.write_coupling_crc(bank, p.crc)
    store.write_imu_set_id(bank, p.imu_set_id)
    return p


def all_on(bank: str, coupling: str | None) -> int:
    return pack_active(dict.fromkeys(AXES, bank), coupling)


def with_matrix(imu, matrix) -> CouplingPayload:
    """A coupling bank for ``imu`` whose matrix is ``matrix`` (CRC and IMU set id made to match)."""
    envelope = {k: v for k, v in imu.to_dict().items() if k != "axes"}
    envelope["coupling"] = {**envelope["coupling"], "matrix": matrix}
    content = canonical_bytes(envelope)
    whole = {**envelope, "axes": {c.axis: c.to_dict() for c in imu.axes}}
    return CouplingPayload(content, zlib.crc32(content), zlib.crc32(canonical_bytes(whole)))


# --------------------------------------------------------------------------------------------
# The object dictionary, the selector and the coupling bank's bytes
# --------------------------------------------------------------------------------------------


def cut_off(c: ImuClient, *, at_download: tuple[int, int] | None = None, at_selector: bool = False) -> None:
    """Make the device fall silent (:class:`DeviceSilent`) at one SDO download of ``c``'s, or at its
    selector write: a tool that dies mid-push."""
    real_download, real_write = c.download, c.write_uint
    selector = imu_objects().active_banks

    def download(key, data, what):  # type: ignore[no-untyped-def]
        if key == at_download:
            raise DeviceSilent("gone")
        real_download(key, data, what)

    def write_uint(key, value, size, what):  # type: ignore[no-untyped-def]
        if at_selector and key == selector:
            raise DeviceSilent("gone")
        real_write(key, value, size, what)

    c.download, c.write_uint = download, write_uint  # type: ignore[method-assign]


def test_coupling_objects_are_in_the_eds_apart_from_every_other() -> None:
    from canopen.objectdictionary import DOMAIN, UNSIGNED32

    od = object_dictionary(NODE)
    o = imu_objects()
    used = {(b.index, s) for b in o.banks.values() for s in (b.content, b.crc, b.status, b.size)}
    used |= {o.active_banks, o.stored_state, *o.active_set_id.values()}
    for bank, index in (("A", 0x2216), ("B", 0x2217)):
        ref = o.coupling_bank(bank)
        keys = {(ref.index, s) for s in (ref.content, ref.crc, ref.status, ref.size, ref.imu_set_id)}
        assert ref.index == index and len(keys) == 5 and not keys & used
        assert od[index][ref.content].data_type == DOMAIN and od[index][ref.content].writable
        assert od[index][ref.imu_set_id].data_type == UNSIGNED32 and od[index][ref.imu_set_id].writable
        assert not od[index][ref.status].writable
        used |= keys
    assert o.active_imu_set_id == (0x2225, 0) and o.active_imu_set_id not in used
    assert not od[0x2225].writable


@pytest.mark.parametrize("coupling", [None, "A", "B"])
def test_selector_carries_the_coupling_in_bits_6_7(coupling) -> None:
    value = all_on("B", coupling)
    assert unpack_active(value) == dict.fromkeys(AXES, "B") and unpack_coupling(value) == coupling
    assert value >> 6 == (0 if coupling is None else 1 + "AB".index(coupling))
    assert pack_active(dict.fromkeys(AXES, "B")) == all_on("B", None) < 0x40  # no coupling: as before


@pytest.mark.parametrize("seed", SEEDS)
def test_coupling_payload_is_the_imu_set_without_its_axes(seed: int) -> None:
    imu = imu_triad_set(seed)
    p = encode_coupling(imu)
    assert p.imu_set_id == imu_file.imu_set_crc(imu) and p.crc == zlib.crc32(p.content)
    envelope = decode_coupling(p.content, p.crc, "bank")
    assert "axes" not in envelope.fields and envelope.matrix == imu.coupling
    assert envelope.fields["coupling"]["matrix"] == [list(r) for r in imu.coupling]


# --------------------------------------------------------------------------------------------
# The bank store's rules for the coupling
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("seed", SEEDS)
def test_axes_and_coupling_activate_in_one_write(seed: int) -> None:
    imu = imu_triad_set(seed)
    store = BankStore(LIMITS, 16384)
    p = load(store, imu)
    assert store.check_coupling("A").status == STATUS_VALID
    store.activate(all_on("A", "A"))
    assert store.active_imu_set_id() == p.imu_set_id == imu_file.imu_set_crc(imu)
    assert store.active_imu_set() == imu and store.activation_count == 1


def test_a_device_without_coupling_runs_the_identity() -> None:
    store = BankStore(LIMITS, 16384)
    load(store, imu_triad_set(0))
    store.activate(all_on("A", None))
    assert store.active_imu_set() is None and store.active_imu_set_id() == 0
    assert store.active_value() == pack_active(dict.fromkeys(AXES, "A"))


@pytest.mark.parametrize(("matrix", "reason"), [
    ([[1.0, 0.12, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], r"coupling term xy is +12.0 %, above 10 %"),
    ([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]], "coupling term zz is 0, outside 0.5..2"),
    ([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 2e-4]], "coupling term zz is 0.0002, outside 0.5..2"),
    ([[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]], "coupling term xx is -1, outside 0.5..2"),
    ([[1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]], "3 rows of 3 finite numbers"),
])
def test_an_implausible_coupling_is_refused_with_an_abort(matrix, reason: str) -> None:
    imu = imu_triad_set(0)
    store = BankStore(LIMITS, 16384)
    load(store, imu, payload=with_matrix(imu, matrix))
    assert store.check_coupling("A").status == STATUS_REFUSED
    store.activate(all_on("A", None))  # the axes alone are fine
    with pytest.raises(BankRefusal) as refused:
        store.activate(all_on("A", "A"))
    assert refused.value.code == ABORT_REFUSED and reason in store.last_refusal
    assert store.active_coupling is None and store.activation_count == 1


def test_a_non_finite_coupling_is_refused() -> None:
    imu = imu_triad_set(0)
    store = BankStore(LIMITS, 16384)
    good = encode_coupling(imu)
    bad = good.content.replace(b'"matrix":[[', b'"matrix":[[NaN,', 1)
    load(store, imu, payload=CouplingPayload(bad, zlib.crc32(bad), good.imu_set_id))
    assert store.check_coupling("A").status == STATUS_REFUSED and "NaN" in store.check_coupling("A").reason
    with pytest.raises(BankRefusal) as refused:
        store.activate(all_on("A", "A"))
    assert refused.value.code == ABORT_REFUSED and store.active_value() == 0


@pytest.mark.parametrize("seed", SEEDS)
def test_a_coupling_is_refused_with_axes_it_does_not_belong_to(seed: int) -> None:
    """Another IMU set's axes, one axis missing, or a declared id that is not the set's."""
    imu, other = imu_triad_set(seed), imu_triad_set(seed + 10)
    store = BankStore(LIMITS, 16384)
    load(store, other, "A", axes=True, payload=encode_coupling(other))
    load(store, imu, "B", axes=False)  # imu's coupling in bank B, the axes of `other` in bank A
    with pytest.raises(BankRefusal) as refused:
        store.activate(all_on("A", "B"))
    assert refused.value.code == ABORT_REFUSED and "belongs to IMU set" in store.last_refusal
    with pytest.raises(BankRefusal):
        store.activate(pack_active({"x": "A", "y": "A"}, "A"))
    assert "needs all three axes" in store.last_refusal
    assert store.active_value() == 0 and store.activation_count == 0
    store.activate(all_on("A", "A"))  # its own axes: accepted
    assert store.active_imu_set() == other


def test_a_coupling_for_another_sensor_is_refused() -> None:
    imu = imu_triad_set(0)
    store = BankStore(LIMITS, 16384)
    load(store, imu, payload=encode_coupling(replace(imu, sensor_id="4712")))
    assert "serial 4711" in store.check_coupling("A").reason
    with pytest.raises(BankRefusal):
        store.activate(all_on("A", "A"))


def test_the_active_coupling_is_neither_overwritten_nor_dropped_nor_split_from_its_axes() -> None:
    imu = imu_triad_set(0)
    store = BankStore(LIMITS, 16384)
    p = load(store, imu)
    store.activate(all_on("A", "A"))
    for write in (lambda: store.write_coupling_content("A", b"{}"), lambda: store.write_coupling_crc("A", 1),
                  lambda: store.write_imu_set_id("A", 1)):
        with pytest.raises(BankRefusal) as refused:
            write()
        assert refused.value.code == ABORT_DEVICE_STATE
    with pytest.raises(BankRefusal) as refused:
        store.activate(all_on("A", None))
    assert refused.value.code == ABORT_VALUE_RANGE
    content, crc = encode_set(imu_set("z", family=1))  # a single-axis set under the coupling
    store.write_content("z", "B", content)
    store.write_crc("z", "B", crc)
    with pytest.raises(BankRefusal) as refused:
        store.activate(pack_active({"x": "A", "y": "A", "z": "B"}, "A"))
    assert refused.value.code == ABORT_REFUSED and "belongs to IMU set" in store.last_refusal
    assert store.active_imu_set_id() == p.imu_set_id and store.active_value() == all_on("A", "A")


def test_power_cycle_keeps_the_stored_coupling_and_drops_a_damaged_one(tmp_path: Path) -> None:
    imu, newer = imu_triad_set(0), imu_triad_set(1)
    state = tmp_path / "imu.json"
    store = BankStore.boot(LIMITS, 16384, state)
    p = load(store, imu)
    store.activate(all_on("A", "A"))
    store.store(True)
    load(store, newer, "B")
    store.activate(all_on("B", "B"))  # activated, not stored
    again = BankStore.boot(LIMITS, 16384, state)
    assert again.active_value() == all_on("A", "A") and again.active_imu_set_id() == p.imu_set_id
    assert again.active_imu_set() == imu and again.stored_value() == all_on("A", "A")
    content = json.loads(state.read_text())
    content["coupling"]["A"]["imu_set_id"] ^= 1  # damaged: no longer the IMU set its axes make
    state.write_text(json.dumps(content))
    damaged = BankStore.boot(LIMITS, 16384, state)
    assert damaged.active == dict.fromkeys(AXES, "A") and damaged.active_coupling is None
    restored = BankStore.boot(LIMITS, 16384, state)
    restored.restore_defaults(True)
    assert BankStore.boot(LIMITS, 16384, state).active_value() == 0


# --------------------------------------------------------------------------------------------
# Over CANopen SDO: push, pull, an interrupted push, the emulated IMU's rates, the DCF
# --------------------------------------------------------------------------------------------


@contextlib.contextmanager
def emulated(tmp_path: Path, name: str = "imu.json") -> Iterator[tuple[EmulatedImu, str]]:
    channel = f"imuset-{uuid.uuid4().hex}"
    net = canopen.Network()
    net.connect(interface="virtual", channel=channel, receive_own_messages=False)
    try:
        config = EmulatorConfig(node_id=NODE, serial=SERIAL, state_path=tmp_path / name)
        yield EmulatedImu(config, net), channel
    finally:
        net.disconnect()


@contextlib.contextmanager
def client(channel: str) -> Iterator[ImuClient]:
    net = canopen.Network()
    net.connect(interface="virtual", channel=channel, receive_own_messages=False)
    try:
        yield ImuClient(net, NODE, 2.0)
    finally:
        net.disconnect()


def bus(channel: str) -> list[str]:
    return ["--node", hex(NODE), "--interface", "virtual", "--channel", channel, "--timeout", "2"]


def one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_push_and_pull_an_imu_set(tmp_path: Path, capsys) -> None:
    first, second = imu_triad_set(0), imu_triad_set(1)
    paths = []
    for k, imu in enumerate((first, second)):
        paths.append(tmp_path / f"imu{k}.yaml")
        imu_file.save(paths[-1], imu)
    with emulated(tmp_path) as (dev, channel):
        assert main(["push", str(paths[0]), *bus(channel), "--dry-run"]) == 0
        out = capsys.readouterr().out
        assert f"IMU set 0x{imu_file.imu_set_crc(first):08x}: coupling" in out and "nothing written" in out
        assert dev.store.activation_count == 0
        for k, imu in enumerate((first, second)):
            assert main(["push", str(paths[k]), *bus(channel)]) == 0
            printed = capsys.readouterr().out
            assert f"coupling of IMU set 0x{imu_file.imu_set_crc(imu):08x}" in printed
            bank = "AB"[k]
            assert dev.store.active_value() == all_on(bank, bank)  # axes and coupling: the other banks
            back = tmp_path / f"back{k}.yaml"
            assert main(["pull", *bus(channel), "--imu-set", "-o", str(back)]) == 0
            pulled = imu_file.load(back)
            assert pulled == imu and imu_file.imu_set_crc(pulled) == imu_file.imu_set_crc(imu)
        assert dev.store.activation_count == 2
        # one axis cannot be replaced under the coupling: refused before anything is written
        single = tmp_path / "z.yaml"
        from canical.sets import coefficient_file

        coefficient_file.save(single, imu_set("z", family=1))
        assert main(["push", str(single), *bus(channel)]) == 2
        assert "runs IMU set" in one_line(capsys) and dev.store.activation_count == 2
        # its single-axis sets still pull as before
        assert main(["pull", *bus(channel), "-o", str(tmp_path / "s-{axis}.yaml")]) == 0
        assert coefficient_file.load(tmp_path / "s-y.yaml") == second.axes[1]
    with emulated(tmp_path) as (dev, channel):  # a power cycle: the stored IMU set comes back
        assert dev.store.active_imu_set() == second
        with client(channel) as c:
            assert pull_imu_set(c) == second and c.status().imu_set_id == imu_file.imu_set_crc(second)


def test_pull_imu_set_from_a_device_without_coupling_is_one_line(tmp_path: Path, capsys) -> None:
    with emulated(tmp_path) as (_dev, channel):
        with client(channel) as c:
            push_sets(c, {a: (a, imu_set(a)) for a in AXES})
        out = tmp_path / "imu.yaml"
        assert main(["pull", *bus(channel), "--imu-set", "-o", str(out)]) == 2
        assert "runs no IMU set" in one_line(capsys) and not out.exists()


@pytest.mark.parametrize("stop_at", ["coupling", "selector"])
def test_an_interrupted_push_leaves_the_old_state(tmp_path: Path, stop_at: str) -> None:
    """The tool dies before the coupling bank is written, or before the selector write: the
    device keeps running the IMU set it ran, axes and coupling, never a mix."""
    old, new = imu_triad_set(0), imu_triad_set(2)
    o = imu_objects()
    with emulated(tmp_path) as (dev, channel):
        with client(channel) as c:
            push_sets(c, {}, imu=("old.yaml", old))
        before = (dev.store.active_value(), {a: dev.store.active_id(a) for a in AXES},
                  dev.store.active_imu_set_id(), dev.store.activation_count)
        with client(channel) as c:
            coupling_content = (o.coupling_bank("B").index, o.coupling_bank("B").content)
            cut_off(c, at_download=coupling_content if stop_at == "coupling" else None,
                    at_selector=stop_at == "selector")
            with pytest.raises(DeviceSilent):
                push_sets(c, {}, imu=("new.yaml", new))
        after = (dev.store.active_value(), {a: dev.store.active_id(a) for a in AXES},
                 dev.store.active_imu_set_id(), dev.store.activation_count)
        assert after == before and dev.store.active_imu_set() == old


@pytest.mark.parametrize("seed", SEEDS)
def test_the_emulated_imu_couples_its_corrected_rates(tmp_path: Path, seed: int) -> None:
    """IMU_RATE as the device sends it (C evaluator, three-axis sample) against `canical apply`'s
    ImuCorrector, within the frame's resolution."""
    imu = imu_triad_set(seed)
    with emulated(tmp_path) as (dev, channel):
        with client(channel) as c:
            push_sets(c, {}, imu=("imu.yaml", imu))
        dev.coupled = dev.device_coupling()
        assert dev.coupled is not None
        rng = np.random.default_rng(seed)
        raw = np.column_stack([rng.integers(int(c.span_raw[0]), int(c.span_raw[1]), 50) for c in imu.axes])
        expected, _ = ImuCorrector(imu).correct(raw.astype(float))
        per_axis, _ = ImuCorrector(imu).per_axis(raw.astype(float))
        coupled = 0
        for k, counts in enumerate(raw):
            aux_id, aux_data = dev.frames.aux(12.0, 0.01 * k, k)
            raw_id, raw_data = dev.frames.raw(tuple(int(v) for v in counts), 25.0, k)
            rate_id, rate_data = dev._corrected({}, 0, raw_id, raw_data, aux_id, aux_data, k)
            values = dev.frames.decode(rate_id, rate_data).values  # type: ignore[union-attr]
            got = np.array([values[f"Rate{a.upper()}"] for a in AXES], dtype=float)
            assert np.abs(got - expected[k]).max() <= 0.0051  # the frame's 0.01 deg/s LSB
            coupled += np.abs(got - per_axis[k]).max() > 0.02
        assert coupled > 10  # the coupling moved the rates by more than the frame's resolution


def test_dcf_of_an_imu_set_carries_the_coupling_and_activates_it(tmp_path: Path) -> None:
    from test_dcf_export import download, variables

    imu = imu_triad_set(1)
    path, dcf = tmp_path / "imu.yaml", tmp_path / "imu.dcf"
    imu_file.save(path, imu)
    assert main(["export", "dcf", str(path), "-o", str(dcf), "--bank", "B"]) == 0
    p = encode_coupling(imu)
    ref = imu_objects().coupling_bank("B")
    values = variables(canopen.import_od(str(dcf), NODE))
    assert values[(ref.index, ref.content)].value == p.content
    assert values[(ref.index, ref.crc)].value == p.crc
    assert values[(ref.index, ref.imu_set_id)].value == p.imu_set_id
    assert values[imu_objects().active_banks].value == all_on("B", "B")
    with emulated(tmp_path) as (dev, channel):
        net = canopen.Network()
        net.connect(interface="virtual", channel=channel, receive_own_messages=False)
        try:
            net.add_node(NODE, str(dcf))
            assert download(net[NODE]) == 2 * len(AXES) + 3 + 1  # axes, coupling bank, the selector
        finally:
            net.disconnect()
        assert dev.store.active_imu_set() == imu and dev.store.active_value() == all_on("B", "B")


def test_command_line_mistakes_are_one_line_and_write_nothing(tmp_path: Path, capsys) -> None:
    imu = tmp_path / "imu.yaml"
    imu_file.save(imu, imu_triad_set(0))
    from canical.sets import coefficient_file

    single = tmp_path / "x.yaml"
    coefficient_file.save(single, imu_set("x"))
    with emulated(tmp_path) as (dev, channel):
        assert main(["push", str(imu), str(single), *bus(channel)]) == 2
        assert "is an IMU set (three axes and their coupling): give it alone" in one_line(capsys)
        out = tmp_path / "out.yaml"
        assert main(["pull", *bus(channel), "--imu-set", "--axis", "x", "-o", str(out)]) == 2
        assert "no --axis with it" in one_line(capsys)
        assert main(["pull", *bus(channel), "--imu-set", "-o", str(tmp_path / "o-{axis}.yaml")]) == 2
        assert "writes one file" in one_line(capsys)
        assert dev.store.activation_count == 0 and sorted(p.name for p in tmp_path.iterdir()) == [
            "imu.yaml", "x.yaml"]


# --------------------------------------------------------------------------------------------
# The daemon with device: the IMU set the device runs, whole
# --------------------------------------------------------------------------------------------


@pytest.mark.parametrize("configured", ["imu_set", "per-axis files"])
def test_the_daemon_takes_the_imu_set_the_device_runs(tmp_path: Path, capsys, configured: str) -> None:
    """At start (and on SIGHUP) a daemon with ``device:`` reads the device's IMU set (axes and
    coupling, one id) whether its own files are an IMU set or per-axis sets; a device without
    one leaves it on its files."""
    from support.daemon_fixtures import write_config

    from canical.bus import active_sets
    from canical.bus.daemon_config import load_config
    from canical.sets import coefficient_file

    on_device, on_file = imu_triad_set(0), imu_triad_set(1)
    imu_file.save(tmp_path / "imu.yaml", on_device)
    imu_file.save(tmp_path / "file.yaml", on_file)
    if configured == "imu_set":
        files = {"axes": {a: {"raw": f"GyroRaw{a.upper()}"} for a in AXES},
                 "imu_set": str(tmp_path / "file.yaml")}
    else:
        for axis, cset in zip(AXES, on_file.axes, strict=True):
            coefficient_file.save(tmp_path / f"imu-{axis}.yaml", cset)
        files = {}
    with emulated(tmp_path) as (_, channel):
        cfg = write_config(tmp_path, channel, interface="virtual", sensor=None, inputs={},
                           device={"node": NODE, "timeout_s": 2.0}, **files)
        config = load_config(cfg)
        before, _ = active_sets.initial(config)  # the device runs no IMU set yet: the files
        assert before.coupling == (on_file.coupling if configured == "imu_set" else None)
        assert before.combined_id != imu_file.imu_set_crc(on_device)
        assert main(["push", str(tmp_path / "imu.yaml"), *bus(channel)]) == 0
        sets, messages = active_sets.initial(config)
    assert sets.coupling == on_device.coupling and sets.combined_id == imu_file.imu_set_crc(on_device)
    assert [ax.source for ax in sets.axes] == [active_sets.SOURCE_DEVICE] * 3
    assert any(f"imu set 0x{sets.combined_id:08x} from device node 0x{NODE:02x}" in m.text for m in messages)
