"""The daemon's parts that need no bus: configuration, codecs, set swapping, sd_notify, CLI errors."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

import can
import numpy as np
import pytest
import yaml
from support.daemon_fixtures import DBC, EXAMPLE_CONFIG, imu_stream, write_config, write_sets
from test_daemon_compiled import feed

from canical.bus import active_sets
from canical.bus.daemon import Daemon
from canical.bus.daemon_config import load_config
from canical.bus.link import BusLink
from canical.bus.sd_notify import Notifier
from canical.errors import CanicalError
from canical.files.atomic_file import write_text_atomic
from canical.frames.codec import RateEncoder, StatusEncoder, load_dbc


@pytest.fixture
def setup(tmp_path: Path):
    sets = write_sets(tmp_path)
    return tmp_path, sets, write_config(tmp_path, "vcan0")


def test_example_config_loads_as_deployed(setup) -> None:
    """services/canical-can0.yaml, pointed at a folder: every key understood, every signal found."""
    _, _, path = setup
    config = load_config(path, channel="can7")
    assert (config.interface, config.channel, config.sensor) == ("socketcan", "can7", "IMU-0001")
    assert set(config.inputs) == {"temp_c", "supply_v", "time_s"}
    assert config.inputs["time_s"].message == "IMU_AUX" and config.inputs["time_s"].signal == "Uptime"
    assert [a.raw_signal for a in config.axes] == ["GyroRawX", "GyroRawY", "GyroRawZ"]


@pytest.mark.parametrize(
    ("change", "key"),
    [
        (lambda c: c["bus"].pop("interface"), "bus.interface"),
        (lambda c: c["bus"].update(chanel="can0"), "bus.chanel"),
        (lambda c: c.update(dbc="missing.dbc"), "dbc"),
        (lambda c: c["frames"].update(raw="IMU_RAWW"), "frames.raw"),
        (lambda c: c["axes"]["y"].update(raw="GyroRawQ"), "axes.y.raw"),
        (lambda c: c["inputs"]["temp_c"].update(signal="IMU_RAW.Temp"), "inputs.temp_c.signal"),
        (lambda c: c["inputs"]["temp_c"].update(signal="Temperature"), "inputs.temp_c.signal"),
        (lambda c: c["inputs"]["time_s"].update(max_age_s=-1), "inputs.time_s.max_age_s"),
        (lambda c: c.update(status_period_s="often"), "status_period_s"),
        (lambda c: c["bus"]["options"].update(can_filters=[]), "bus.options.can_filters"),
        (lambda c: c.update(counter="Count"), "counter"),
    ],
)
def test_bad_config_refused_with_one_line_naming_the_key(setup, change, key: str) -> None:
    folder, _, path = setup
    content = yaml.safe_load(path.read_text())
    change(content)
    bad = folder / "bad.yaml"
    bad.write_text(yaml.safe_dump(content))
    proc = subprocess.run([sys.executable, "-m", "canical", "serve", "--config", str(bad)],
                          capture_output=True, text=True, timeout=60, check=False)
    assert proc.returncode == 2
    lines = proc.stderr.strip().splitlines()
    assert len(lines) == 1 and f": {key}: " in lines[0], proc.stderr
    assert not proc.stdout


def test_check_loads_every_set(setup) -> None:
    _, sets, path = setup
    ok = subprocess.run([sys.executable, "-m", "canical", "serve", "--config", str(path), "--check"],
                        capture_output=True, text=True, timeout=60, check=False)
    assert ok.returncode == 0 and "configuration OK" in ok.stdout, ok.stderr
    sets["y"].write_text(sets["y"].read_text().replace("v0: ", "v0: 1"))
    bad = subprocess.run([sys.executable, "-m", "canical", "serve", "--config", str(path), "--check"],
                         capture_output=True, text=True, timeout=60, check=False)
    assert bad.returncode == 2 and "CRC mismatch" in bad.stderr


def test_set_for_wrong_axis_sensor_or_unmapped_input_is_refused(setup) -> None:
    folder, sets, path = setup
    config = load_config(path)
    with pytest.raises(CanicalError, match="configured for axis y"):
        active_sets.load_axis(config, "y", sets["x"])
    content = yaml.safe_load(path.read_text())
    content["sensor"] = "IMU-0002"
    (folder / "other.yaml").write_text(yaml.safe_dump(content))
    other = load_config(folder / "other.yaml")
    with pytest.raises(CanicalError, match="configured sensor is IMU-0002"):
        active_sets.load_axis(other, "x", sets["x"])
    del content["inputs"]["temp_c"]
    content["sensor"] = "IMU-0001"
    (folder / "noinput.yaml").write_text(yaml.safe_dump(content))
    with pytest.raises(CanicalError, match=r"needs input.*temp_c, not mapped"):
        active_sets.load_axis(load_config(folder / "noinput.yaml"), "x", sets["x"])


def test_reload_replaces_whole_value_and_keeps_unchanged_correctors(setup) -> None:
    """A changed file gives a new ActiveSets; unchanged axes keep their Corrector (and its state);
    a damaged file leaves its axis as it was."""
    folder, sets, path = setup
    config = load_config(path)
    first, messages = active_sets.initial(config)
    assert first.complete and len(messages) == 3
    same, _ = active_sets.reload(config, first, force=False)
    assert same is first
    (folder / "g1").mkdir()
    new_sets = write_sets(folder / "g1", variant=1)
    write_text_atomic(sets["x"], new_sets["x"].read_text())
    second, messages = active_sets.reload(config, first, force=False)
    assert second is not first and second.axes[0].set_id != first.axes[0].set_id
    assert second.axes[1].corrector is first.axes[1].corrector
    assert second.axes[0].reloads == 1 and second.combined_id != first.combined_id
    write_text_atomic(sets["z"], "not: a set\n")
    third, messages = active_sets.reload(config, second, force=False)
    assert third.axes[2].corrector is second.axes[2].corrector
    assert [(m.refused, "keeping set" in m.text) for m in messages if m.text.startswith("axis z:")] == [
        (True, True)]  # a refused set is a warning's news
    again, messages = active_sets.reload(config, third, force=False)
    assert again is third and not messages  # the damaged file is reported once, not every poll


def test_rate_encoder_saturates_instead_of_failing() -> None:
    db = load_dbc(DBC)
    msg = db.get_message_by_name("CANICAL_RATE")
    enc = RateEncoder(msg)
    data = enc.encode([1e6, -1e6, 12.345], [True, True, False], [False, False, True], True, False, 9, 15)
    d = msg.decode(data)
    assert (d["RateX"], d["RateY"]) == pytest.approx((327.67, -327.68))
    assert d["RateZ"] == pytest.approx(12.34, abs=0.0051)
    assert (d["OutOfSpanX"], d["UncalibratedZ"], d["Stale"], d["SetTag"], d["Counter"]) == (1, 1, 1, 9, 15)


def test_status_pages_fill_missing_signals_and_wrap_counters() -> None:
    msg = load_dbc(DBC).get_message_by_name("CANICAL_STATUS")
    enc = StatusEncoder(msg)
    assert enc.pages == (0, 1, 2, 3)  # 3: the learned bias, sent with bias_tracking on
    d = msg.decode(enc.encode(0, {"FramesIn": 70_000, "BusErrors": 300}), decode_choices=False)
    assert (d["FramesIn"], d["BusErrors"], d["FramesOut"]) == (70_000 - 65_536, 300 - 256, 0)


def test_notifier_speaks_to_abstract_and_path_sockets(tmp_path: Path) -> None:
    for address in ("@canical-notify-test", str(tmp_path / "notify")):
        server = socket.socket(socket.AF_UNIX, socket.SOCK_DGRAM)
        server.bind(b"\0" + address[1:].encode() if address.startswith("@") else address)
        notifier = Notifier({"NOTIFY_SOCKET": address, "WATCHDOG_USEC": "3000000",
                             "WATCHDOG_PID": str(os.getpid())})
        assert notifier.enabled and notifier.watchdog_s == pytest.approx(1.5)
        assert notifier.ready("running: 0 frames")
        assert notifier.watchdog()
        assert server.recv(100) == b"READY=1\nSTATUS=running: 0 frames"
        assert server.recv(100) == b"WATCHDOG=1"
        notifier.close()
        server.close()
    assert not Notifier({}).enabled and not Notifier({}).send(READY=1)
    assert Notifier({"WATCHDOG_USEC": "1000", "WATCHDOG_PID": "1"}).watchdog_s is None  # for another pid


def daemon_on_fake_bus(path) -> tuple[Daemon, list[can.Message]]:
    """A daemon with its sets loaded whose bus only collects what it sends."""
    daemon = Daemon(load_config(path))
    daemon.load_sets()
    sent: list[can.Message] = []

    class FakeBus:
        def send(self, msg: can.Message, timeout: float | None = None) -> None:
            sent.append(msg)

    daemon.sender.link = BusLink(FakeBus())  # type: ignore[arg-type]
    return daemon, sent


def test_dispatch_counts_what_it_drops(setup) -> None:
    """In-process (no kernel filter, as with interfaces that filter in software): every kind of
    frame that is not a good raw or input frame is counted and produces nothing."""
    _, _, path = setup
    daemon, sent = daemon_on_fake_bus(path)
    stream = imu_stream(30)
    msgs = [can.Message(arbitration_id=fid, data=data, is_extended_id=False, timestamp=1.0)
            for fid, data in stream.frames]
    raw = stream.frames[stream.raw_index[0]][1]
    feed(daemon, [*msgs,
        can.Message(arbitration_id=0x190, data=raw[:5], is_extended_id=False),
        can.Message(arbitration_id=0x555, data=raw, is_extended_id=False),
        can.Message(arbitration_id=0x190, data=raw, is_extended_id=True),
        can.Message(arbitration_id=0x190, is_remote_frame=True, dlc=8, is_extended_id=False),
        can.Message(arbitration_id=0x190, data=raw + bytes(8), is_fd=True, is_extended_id=False),
        can.Message(arbitration_id=0x4, is_error_frame=True),
    ])
    s = daemon.stats
    assert (s.frames_in, s.frames_out, len(sent)) == (30, 30, 30)
    assert (s.bad_length, s.unknown_ids, s.remote_frames, s.fd_frames, s.error_frames) == (1, 2, 1, 1, 1)
    rate = load_dbc(DBC).get_message_by_name("CANICAL_RATE")
    assert all(m.arbitration_id == rate.frame_id for m in sent)
    values = [rate.decode(m.data) for m in sent]
    assert all(np.isfinite(v["RateX"]) and not v["UncalibratedX"] for v in values)


def test_example_config_is_the_one_tests_use() -> None:
    assert EXAMPLE_CONFIG.is_file() and "/etc/canical/" in EXAMPLE_CONFIG.read_text()


def test_input_never_received_marks_only_the_axes_that_need_it(setup) -> None:
    """Before the first IMU_AUX frame there is no time_s: axis x (warm-up term) goes out
    uncalibrated and every frame is Stale; y and z, which need no such input, are corrected."""
    _, _, path = setup
    daemon, sent = daemon_on_fake_bus(path)
    stream = imu_stream(20)
    feed(daemon, [can.Message(arbitration_id=fid, data=data, is_extended_id=False, timestamp=1.0)
                  for fid, data in stream.frames if fid == 0x190])
    rate = load_dbc(DBC).get_message_by_name("CANICAL_RATE")
    values = [rate.decode(m.data) for m in sent]
    assert len(values) == 20
    assert all(v["UncalibratedX"] == 1 and v["RateX"] == 0 and v["Stale"] == 1 for v in values)
    assert not any(v["UncalibratedY"] or v["UncalibratedZ"] for v in values)
