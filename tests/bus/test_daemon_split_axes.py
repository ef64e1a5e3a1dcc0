"""A vendor's IMU that sends each gyro axis in its own message (standard and extended ids, Intel
and Motorola, no counter): the daemon holds each axis's latest value and corrects all three when
the raw frame (the last axis's message) comes; ``apply --config`` on a log of the same frames
gives the same rates.
"""

from __future__ import annotations

from pathlib import Path

import can
import numpy as np
import pytest
import yaml
from support.daemon_fixtures import DBC, TERMS, write_sets
from test_daemon_compiled import StandInSocket, feed, handler_source, kernel_frame, serve_socket

from canical.bus.daemon import Daemon
from canical.bus.daemon_config import load_config
from canical.bus.link import BusLink
from canical.commands.cli import main
from canical.errors import CanicalError
from canical.frames.codec import load_dbc
from canical.sessions.csv_file import read_table
from canical.sets import coefficient_file
from canical.sets.corrector import Corrector

SPLIT = Path(__file__).resolve().parents[1] / "data" / "vendor_imu_split.dbc"
FS = 200.0
AXIS_SIGNALS = {"x": "ROLL_RATE.RollRaw", "y": "PITCH_RATE.PitchRaw", "z": "YAW_RATE.YawRaw"}
HALF_LSB = 0.005 + 1e-9


@pytest.fixture
def sets(tmp_path: Path) -> dict[str, Path]:
    """A temperature term on x: its input comes from the z axis's message."""
    return write_sets(tmp_path, terms={"x": TERMS["x"][:1], "y": (), "z": TERMS["y"]})


def split_config(folder: Path, sets: dict[str, Path], **changes) -> Path:
    content = {
        "bus": {"interface": "socketcan", "channel": "split"},
        "dbc": str(SPLIT),
        "axes": {a: {"raw": AXIS_SIGNALS[a], "coefficients": str(sets[a])} for a in "xyz"},
        "inputs": {"temp_c": {"signal": "YAW_RATE.ChipTemp", "max_age_s": 1.0}},
    }
    content.update(changes)
    path = folder / "split.yaml"
    path.write_text(yaml.safe_dump(content, sort_keys=False))
    return path


def split_stream(n: int, seed: int = 4, gap: tuple[int, int] = (0, 0)) -> list[can.Message]:
    """``n`` samples, each as ROLL, PITCH, YAW frames 0.2 ms apart; the ROLL frames of samples
    in ``gap`` are lost (the x axis's value goes stale)."""
    db = load_dbc(SPLIT)
    roll, pitch, yaw = (db.get_message_by_name(m) for m in ("ROLL_RATE", "PITCH_RATE", "YAW_RATE"))
    rng = np.random.default_rng(seed)
    t = np.arange(n) / FS
    counts = np.column_stack([24000 * np.sin(2 * np.pi * (t / t[-1] + k / 3)) + rng.normal(0, 30, n)
                              for k in range(3)]).astype(int)
    temp = 25.0 + 5.0 * np.sin(2 * np.pi * t / t[-1])
    msgs = []
    for i in range(n):
        stamp = 50.0 + t[i]
        if not gap[0] <= i < gap[1]:
            msgs.append(can.Message(timestamp=stamp, arbitration_id=roll.frame_id, is_extended_id=False,
                                    data=roll.encode({"RollRaw": int(counts[i, 0]), "RollQuality": 1})))
        msgs.append(can.Message(timestamp=stamp + 0.0002, arbitration_id=pitch.frame_id, is_extended_id=True,
                                data=pitch.encode({"PitchRaw": int(counts[i, 1]), "PitchQuality": 1})))
        msgs.append(can.Message(timestamp=stamp + 0.0004, arbitration_id=yaw.frame_id, is_extended_id=False,
                                data=yaw.encode({"YawRaw": int(counts[i, 2]), "YawQuality": 1,
                                                 "ChipTemp": round(float(temp[i]), 2)})))
    return msgs


def held_rows(msgs: list[can.Message]) -> list[dict[str, float]]:
    """Per YAW frame, the latest of every message's signals (as the daemon holds them)."""
    db = load_dbc(SPLIT)
    held: dict[str, float] = {}
    rows = []
    for m in msgs:
        held.update(db.get_message_by_frame_id(m.arbitration_id).decode(m.data))
        if m.arbitration_id == 0x1A2:
            rows.append(dict(held))
    return rows


def run(config_path: Path, msgs: list[can.Message]) -> tuple[Daemon, list[bytes], list[bytes]]:
    """The compiled daemon on a stand-in raw socket and the reference one: what each sent."""
    config = load_config(config_path)
    compiled, reference = Daemon(config), Daemon(config, compiled=False)
    sent_ref: list[bytes] = []
    reference.sender.link = BusLink(type("Bus", (), {  # type: ignore[arg-type]
        "send": lambda self, msg, timeout=None: sent_ref.append(bytes(msg.data))})())
    for daemon in (compiled, reference):
        daemon.load_sets()
    feed(reference, msgs)
    sock = StandInSocket(compiled, [(kernel_frame(m), m.timestamp) for m in msgs])
    serve_socket(compiled, sock)
    return compiled, sock.sent, sent_ref


def test_axes_from_three_messages_are_held_and_corrected_at_the_raw_frame(tmp_path: Path, sets) -> None:
    config = load_config(split_config(tmp_path, sets))
    assert config.raw_message == "YAW_RATE" and config.counter_signal is None
    assert [(a.message, a.raw_signal) for a in config.axes] == [
        ("ROLL_RATE", "RollRaw"), ("PITCH_RATE", "PitchRaw"), (None, "YawRaw")]
    msgs = split_stream(600, gap=(300, 340))  # 40 samples (0.2 s) without ROLL: x stale
    compiled, sent, sent_ref = run(tmp_path / "split.yaml", msgs)
    assert sent == sent_ref and len(sent) == 600
    assert "values['@x']" in handler_source(compiled)  # the generated handler, with x held
    rate_msg = load_dbc(DBC).get_message_by_name("CANICAL_RATE")
    got = [rate_msg.decode(p) for p in sent]
    stale = [g["Stale"] for g in got]
    # ROLL lost from sample 300: stale once its last value is older than 0.1 s, until 340.
    assert not any(stale[:300]) and all(stale[321:340]) and not any(stale[341:])
    rows = held_rows(msgs)
    for axis, signal in (("x", "RollRaw"), ("y", "PitchRaw"), ("z", "YawRaw")):
        corrector = Corrector(coefficient_file.load(sets[axis]))
        want = np.array([corrector.correct_one(r[signal], {"temp_c": r["ChipTemp"]})[0] for r in rows])
        sent_rates = np.array([g[f"Rate{axis.upper()}"] for g in got])
        inside = np.abs(want) < 327.0
        assert inside.sum() > 300
        assert np.max(np.abs(sent_rates - want)[inside]) <= HALF_LSB, axis
    assert compiled.stats.stale_frames == sum(stale)
    assert compiled.stats.inputs_in == 560 + 600  # the ROLL and PITCH frames


def test_apply_on_a_log_of_the_frames_gives_the_daemons_rates(tmp_path: Path, sets) -> None:
    msgs = split_stream(400)
    _, sent, _ = run(split_config(tmp_path, sets), msgs)
    log = tmp_path / "drive.log"
    with can.Logger(str(log)) as logger:
        for m in msgs:
            logger.on_message_received(m)
    rate_msg = load_dbc(DBC).get_message_by_name("CANICAL_RATE")
    got = [rate_msg.decode(p) for p in sent]
    for axis in "xyz":
        out = tmp_path / f"apply-{axis}.csv"
        assert main(["apply", str(sets[axis]), str(log), "--config", str(tmp_path / "split.yaml"),
                     "-o", str(out)]) == 0
        table = read_table(out).columns
        assert "@x" not in table and len(table["rate_dps"]) == len(got)
        want = np.clip(table["rate_dps"], -327.68, 327.67)
        assert np.max(np.abs(np.array([g[f"Rate{axis.upper()}"] for g in got]) - want)) <= HALF_LSB, axis


@pytest.mark.parametrize(("change", "words"), [
    ({"own_layout": {"id": 0x2A2}}, "own_layout.ids: the axes come from several messages"),
    ({"own_layout": {"id": 0x2A2, "ids": {"ROLL_RATE": 0x2A0}}}, "own_layout.ids: no id for PITCH_RATE"),
    ({"own_layout": {"id": 0x2A2, "ids": {"ROLL_RATE": 0x2A0, "PITCH_RATE": 0x20000000}}},
     "own_layout.ids.PITCH_RATE: must be a CAN id"),
    ({"own_layout": {"id": 0x2A2, "extended": False, "ids": {"ROLL_RATE": 0x2A2, "PITCH_RATE": 0x18FF0001}}},
     "own_layout.ids: two messages sent at the same id"),
    ({"own_layout": {"id": 0x2A2, "ids": {"ROLL_RATE": 0x1A0, "PITCH_RATE": 0x18FF0001}}},
     "own_layout.ids.ROLL_RATE: 0x1a0 is ROLL_RATE's id on the same bus"),
    ({"axes": {"x": {"raw": "ROLL_RATE.Nope"}}}, "axes.x.raw: signal Nope not in message ROLL_RATE"),
    ({"axes": {"x": {"raw": "YAW_RATE.YawRaw", "max_age_s": 0.5}, "y": {"raw": "PITCH_RATE.PitchRaw"}}},
     "axes.x.max_age_s: only for an axis in another message"),
    ({"inputs": {"@x": "YAW_RATE.ChipTemp"}}, "inputs.@x: an input name cannot start with '@'"),
])
def test_bad_split_configurations_are_one_line(tmp_path: Path, sets, change: dict, words: str) -> None:
    if "axes" in change:
        change = {"axes": {**{a: {"raw": AXIS_SIGNALS[a], "coefficients": str(sets[a])} for a in "xyz"},
                           **{a: {**v, "coefficients": str(sets[a])} for a, v in change["axes"].items()}}}
    with pytest.raises(CanicalError, match=words.replace("(", r"\(").replace("'", ".")):
        load_config(split_config(tmp_path, sets, **change))


OWN = {"id": 0x2A2, "ids": {"ROLL_RATE": 0x2A0, "PITCH_RATE": 0x18FF2A41}}


def test_each_message_goes_out_in_its_own_layout(tmp_path: Path, sets) -> None:
    """own_layout with ids: when the raw frame comes, it and each other message an axis comes in
    (from its latest frame) go out at their ids, the axis's signal its corrected rate (saturated
    and rounded to the signal as cantools encodes), every other signal as it came."""
    msgs = split_stream(300, gap=(100, 101))  # one ROLL lost: its last frame is re-sent
    compiled, sent, sent_ref = run(split_config(tmp_path, sets, own_layout=OWN), msgs)
    assert sent == sent_ref and len(sent) == 4 * 300  # YAW, ROLL, PITCH in their layouts; CANICAL_RATE
    assert "held_frames.get(KEY1)" in handler_source(compiled)
    db = load_dbc(SPLIT)
    rate_msg = load_dbc(DBC).get_message_by_name("CANICAL_RATE")
    layouts = [db.get_message_by_name(m) for m in ("YAW_RATE", "ROLL_RATE", "PITCH_RATE")]
    rows = held_rows(msgs)
    for i, row in enumerate(rows):
        yaw, roll, pitch = (m.decode(p) for m, p in zip(layouts, sent[4 * i:4 * i + 3], strict=True))
        rates = rate_msg.decode(sent[4 * i + 3])
        for own, signal, axis in ((roll, "RollRaw", "X"), (pitch, "PitchRaw", "Y"), (yaw, "YawRaw", "Z")):
            assert abs(own[signal] - rates[f"Rate{axis}"]) <= 0.5 + 0.005, (i, signal)
        assert (roll["RollQuality"], pitch["PitchQuality"], yaw["YawQuality"]) == (1, 1, 1)
        assert yaw["ChipTemp"] == pytest.approx(row["ChipTemp"])


def test_the_own_layouts_of_several_messages_on_the_bus_as_the_daemon_runs(tmp_path: Path, sets) -> None:
    """The same through the daemon's receive loop on python-can's virtual bus (the reference
    path's send): the frames at their ids."""
    msgs = split_stream(50)
    config = load_config(split_config(tmp_path, sets, own_layout=OWN, frames={"rate": None}))
    daemon = Daemon(config, compiled=False)
    daemon.load_sets()
    out: list[can.Message] = []
    daemon.sender.link = BusLink(type("Bus", (), {  # type: ignore[arg-type]
        "send": lambda self, msg, timeout=None: out.append(msg)})())
    feed(daemon, msgs)
    assert [(m.arbitration_id, m.is_extended_id) for m in out[:3]] == [
        (0x2A2, False), (0x2A0, False), (0x18FF2A41, True)]
    assert len(out) == 150 and daemon.stats.frames_out == 50


def test_noise_reads_a_held_axis_from_a_log_with_the_configuration(tmp_path: Path, sets, capsys) -> None:
    """``noise --config`` on a log: the x axis from its own message, one row per raw frame."""
    msgs = split_stream(400)
    split_config(tmp_path, sets)
    log = tmp_path / "static.log"
    with can.Logger(str(log)) as logger:
        for m in msgs:
            logger.on_message_received(m)
    assert main(["noise", str(log), "--coefficients", str(sets["x"]), "--config",
                 str(tmp_path / "split.yaml")]) == 0
    assert "2.0 s at 200 Hz" in capsys.readouterr().out  # 400 rows: every YAW frame


@pytest.mark.vcan
def test_split_axes_through_a_one_way_gateway_equal_apply(vcan_channels: tuple[str, str], tmp_path: Path,
                                                          sets) -> None:
    """On SocketCAN: ROLL (standard, Intel), PITCH (extended, Motorola) and YAW (standard, Motorola)
    frames on vcan0, no counter; each goes out on vcan1 in its own layout, its axis corrected,
    equal to ``apply --config`` on a log of vcan0 (to the signal's resolution); nothing sent on
    vcan1 reaches vcan0."""
    import subprocess
    import sys
    import time

    from support.daemon_fixtures import DaemonProcess, Recorder

    sensor_bus, vehicle_bus = vcan_channels
    n = 300
    path = split_config(tmp_path, sets, bus={"interface": "socketcan", "channel": sensor_bus},
                        own_layout={**OWN, "channel": vehicle_bus})
    msgs = split_stream(n)
    rec_in, rec_out = Recorder(sensor_bus), Recorder(vehicle_bus)
    daemon = DaemonProcess(path)
    try:
        with can.Bus(interface="socketcan", channel=sensor_bus) as tx:
            start = time.monotonic()
            for i, m in enumerate(msgs):
                tx.send(can.Message(arbitration_id=m.arbitration_id, is_extended_id=m.is_extended_id,
                                    data=bytes(m.data)), timeout=1.0)
                lag = start + (i + 1) / 900.0 - time.monotonic()
                if lag > 0:
                    time.sleep(lag)
        rec_out.wait_count(0x18FF2A41, n, timeout=60)
        time.sleep(0.5)
    finally:
        code = daemon.stop()
        seen_in, seen_out = list(rec_in.messages), list(rec_out.messages)
        rec_in.close()
        rec_out.close()
    assert code == 0, daemon.log()
    assert not [m for m in seen_in if m.arbitration_id in (0x2A0, 0x2A2, 0x18FF2A41)]  # one way
    db = load_dbc(SPLIT)
    log = tmp_path / "drive.log"
    with can.Logger(str(log)) as logger:
        for m in seen_in:
            if m.arbitration_id in (0x1A0, 0x1A2, 0x18FF2A40):
                logger.on_message_received(m)
    for axis, (name, out_id, signal) in {"x": ("ROLL_RATE", 0x2A0, "RollRaw"),
                                         "y": ("PITCH_RATE", 0x18FF2A41, "PitchRaw"),
                                         "z": ("YAW_RATE", 0x2A2, "YawRaw")}.items():
        message = db.get_message_by_name(name)
        got = [message.decode(bytes(m.data)) for m in seen_out if m.arbitration_id == out_id]
        assert len(got) == n, (axis, len(got))
        csv = tmp_path / f"apply-{axis}.csv"
        proc = subprocess.run([sys.executable, "-m", "canical", "apply", str(sets[axis]), str(log),
                               "--config", str(path), "-o", str(csv)], capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr
        want = np.clip(read_table(csv).columns["rate_dps"], -32768, 32767)
        assert np.max(np.abs(np.array([g[signal] for g in got]) - want)) <= 0.5 + 1e-6, axis


def test_canical_frames_are_optional(tmp_path: Path, sets) -> None:
    """frames: {rate: null, status: null}: only the IMU's own layout goes out, no frame of canical's."""
    config = load_config(split_config(tmp_path, sets, own_layout=OWN, frames={"rate": None, "status": None}))
    assert (config.rate_message, config.status_message) == (None, None)
    daemon = Daemon(config, compiled=False)
    daemon.load_sets()
    out: list[can.Message] = []
    daemon.sender.link = BusLink(type("Bus", (), {  # type: ignore[arg-type]
        "send": lambda self, msg, timeout=None: out.append(msg)})())
    feed(daemon, split_stream(20))
    daemon._send_status()
    assert {m.arbitration_id for m in out} == {0x2A2, 0x2A0, 0x18FF2A41} and len(out) == 60
    assert "20 frames in" in daemon.status_line()
