"""A J1939 IMU: its rate group is corrected at whatever priority and source address it arrives.

The vendor-like J1939 IMU (tests/data/vendor_imu_j1939.dbc) sends PGN 0xFF2A from source 0x10 in
the DBC; on the vehicle its address is claimed anew and its priority may differ. The reference
handler (python-can messages) and the generated one (stand-in raw socket) must correct every
frame of the group alike; frames of another source are not the IMU's unless configured.
"""

from __future__ import annotations

from pathlib import Path

import can
import cantools
import numpy as np
import pytest
import yaml
from support.daemon_fixtures import write_sets
from test_daemon_compiled import StandInSocket, feed, handler_source, kernel_frame, serve_socket
from test_daemon_own_layout import vendor_stream

from canical.bus.daemon import Daemon
from canical.bus.daemon_config import load_config
from canical.bus.socketcan import receive_filters
from canical.errors import CanicalError

DBC = Path(__file__).resolve().parents[1] / "data" / "vendor_imu_j1939.dbc"
MESSAGE = cantools.database.load_file(str(DBC), strict=False).get_message_by_name("ANGRATE")
SIGNALS = ("RollRate", "PitchRate", "YawRate")


def config_file(folder: Path, **extra) -> Path:
    sets = write_sets(folder, terms={"x": (), "y": (), "z": ()}, raw_units="deg/s")
    content = {
        "bus": {"interface": "virtual", "channel": "j1939"},
        "dbc": str(extra.pop("dbc", DBC)),
        "axes": {a: {"raw": f"ANGRATE.{s}", "coefficients": str(sets[a])} for a, s in zip("xyz", SIGNALS,
                                                                                          strict=True)},
        **extra,
    }
    path = folder / "j1939.yaml"
    path.write_text(yaml.safe_dump(content, sort_keys=False))
    return path


def re_addressed(msgs: list[can.Message], seed: int = 3) -> list[can.Message]:
    """The same frames at random priorities, from source 0x10 or the claimed 0x80."""
    rng = np.random.default_rng(seed)
    out = []
    for m in msgs:
        priority, source = int(rng.integers(0, 8)), int(rng.choice([0x10, 0x80]))
        frame_id = (m.arbitration_id & ~(0x7 << 26) & ~0xFF) | priority << 26 | source
        out.append(can.Message(arbitration_id=frame_id, is_extended_id=True, data=m.data,
                               timestamp=m.timestamp))
    return out


def run_both(config, msgs: list[can.Message]) -> tuple[Daemon, list[can.Message], list[bytes], Daemon]:
    reference, compiled = Daemon(config, compiled=False), Daemon(config)
    sent: list[can.Message] = []

    class RefBus:
        def send(self, msg: can.Message, timeout: float | None = None) -> None:
            sent.append(msg)

    for daemon in (reference, compiled):
        daemon.load_sets()
    feed(reference, msgs, RefBus())
    sock = StandInSocket(compiled, [(kernel_frame(m), m.timestamp) for m in msgs])
    serve_socket(compiled, sock)
    return reference, sent, sock.sent, compiled


def test_any_source_corrects_every_frame_of_the_group(tmp_path: Path) -> None:
    config = load_config(config_file(tmp_path, j1939={"source_address": "any"}))
    msgs = re_addressed(vendor_stream(MESSAGE, 200))
    reference, sent, sock_sent, compiled = run_both(config, msgs)
    assert reference.stats.frames_in == 200 and compiled.stats.frames_in == 200
    assert len(sent) == 200 and sock_sent == [bytes(m.data) for m in sent]
    assert "send" in handler_source(compiled)  # the generated handler corrected them
    (rate_filter,) = [f for f in receive_filters(reference.layout.receive_matches()) if f["extended"]]
    assert rate_filter["can_mask"] == 0x03FFFF00 and rate_filter["can_id"] == 0x00FF2A00


def test_the_dbcs_source_by_default_and_a_configured_one(tmp_path: Path) -> None:
    msgs = re_addressed(vendor_stream(MESSAGE, 200))
    from_dbc = sum((m.arbitration_id & 0xFF) == 0x10 for m in msgs)
    for extra, expected in (({}, from_dbc), ({"j1939": {"source_address": 0x80}}, 200 - from_dbc)):
        config = load_config(config_file(tmp_path, **extra))
        reference, sent, sock_sent, compiled = run_both(config, msgs)
        assert reference.stats.frames_in == expected == compiled.stats.frames_in
        assert reference.stats.unknown_ids == 200 - expected
        assert sock_sent == [bytes(m.data) for m in sent]


@pytest.mark.parametrize(("section", "words"), [
    ({"source_address": 254}, "j1939.source_address: must be 'any' or a source address 0..253"),
    ({"source": "any"}, "j1939.source: unknown key"),
    ("any", "j1939: must be a mapping"),
])
def test_a_bad_j1939_section_is_one_line(tmp_path: Path, section, words: str) -> None:
    with pytest.raises(CanicalError) as info:
        load_config(config_file(tmp_path, j1939=section))
    assert words in str(info.value) and "\n" not in str(info.value)


def test_an_own_layout_id_in_the_group_the_daemon_reads_is_refused(tmp_path: Path) -> None:
    """With any source, the IMU's group sent again from another address would be read back."""
    with pytest.raises(CanicalError) as info:
        load_config(config_file(tmp_path, j1939={"source_address": "any"}, own_layout={"id": 0x18FF2A20}))
    words = "own_layout.id: 0x18ff2a20 is ANGRATE's group (J1939 PGN 0x0ff2a (65322), any source)"
    assert words in str(info.value)
    load_config(config_file(tmp_path, own_layout={"id": 0x18FF2A20}))  # only source 0x10 is read: fine


def test_apply_reads_a_j1939_log_as_the_daemon_reads_the_bus(tmp_path: Path, capsys) -> None:
    """The log's IMU claimed address 0x80: read with the configuration's j1939 section or
    --j1939-source, the same frames and rates as the daemon; with the DBC's source, none."""
    import csv

    from canical.commands.cli import main

    msgs = [m for m in re_addressed(vendor_stream(MESSAGE, 120)) if m.arbitration_id & 0xFF == 0x80]
    log = tmp_path / "drive.log"
    with can.Logger(str(log)) as logger:
        for m in msgs:
            logger.on_message_received(m)
    cfg = config_file(tmp_path, j1939={"source_address": 0x80})
    sets = {a: str(tmp_path / f"imu-{a}.yaml") for a in "xyz"}
    out = tmp_path / "z.csv"
    assert main(["apply", sets["z"], str(log), "--config", str(cfg), "-o", str(out)]) == 0, \
        capsys.readouterr().err
    rows = list(csv.DictReader(line for line in out.read_text().splitlines() if not line.startswith("#")))
    assert len(rows) == len(msgs)
    reference, sent, _, _ = run_both(load_config(cfg), msgs)
    rate_msg = reference.layout.rate_message
    assert rate_msg is not None
    encoded = [rate_msg.decode(m.data) for m in sent if m.arbitration_id == rate_msg.frame_id]
    assert len(encoded) == len(rows)
    assert [round(float(r["rate_dps"]), 2) for r in rows] == [round(d["RateZ"], 2) for d in encoded]

    plain = config_file(tmp_path)
    out.unlink()
    assert main(["apply", sets["z"], str(log), "--config", str(plain), "-o", str(out)]) == 2
    assert "no ANGRATE frames" in capsys.readouterr().err and not out.exists()
    assert main(["apply", sets["z"], str(log), "--config", str(plain), "--j1939-source", "any",
                 "-o", str(out)]) == 0


def bare_dbc(folder: Path) -> Path:
    """The vendor's file as vendors ship it: no ProtocolType, no VFrameFormat (cantools reads no
    message as J1939, so each is matched by its exact id, source 0x10 only)."""
    path = folder / "vendor_bare.dbc"
    text = DBC.read_text()
    path.write_text("\n".join(line for line in text.splitlines() if not line.startswith(("BA_DEF", "BA_ "))))
    return path


def test_a_source_the_bare_dbcs_raw_frame_can_never_match_is_refused_at_check(tmp_path: Path,
                                                                             capsys) -> None:
    """'configuration OK', then no frame ever: the raw frame is matched by its exact id (source
    0x10) while the IMU sends from 0x80. --check says what to add."""
    from canical.commands.cli import main

    cfg = config_file(tmp_path, dbc=str(bare_dbc(tmp_path)), j1939={"source_address": 0x80})
    assert main(["serve", "--config", str(cfg), "--check"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert ("frames.raw: message ANGRATE is matched by its exact id 0x18ff2a10, whose source address "
            "0x10 is not j1939.source_address 0x80: if it is a J1939 parameter group, list it under "
            "j1939.messages (or messages: all)") in err


@pytest.mark.parametrize("messages", [["ANGRATE"], "all"])
def test_the_configuration_says_which_messages_of_a_bare_dbc_are_j1939(tmp_path: Path, capsys,
                                                                       messages) -> None:
    """j1939.messages marks the vendor's groups: the daemon and apply --config then match them by
    PGN from the configured source, as with a DBC that says so itself."""
    from canical.commands.cli import main

    msgs = re_addressed(vendor_stream(MESSAGE, 200))
    claimed = [m for m in msgs if m.arbitration_id & 0xFF == 0x80]
    cfg = config_file(tmp_path, dbc=str(bare_dbc(tmp_path)),
                      j1939={"source_address": 0x80, "messages": messages})
    assert main(["serve", "--config", str(cfg), "--check"]) == 0, capsys.readouterr().err
    reference, sent, sock_sent, compiled = run_both(load_config(cfg), msgs)
    assert reference.stats.frames_in == len(claimed) == compiled.stats.frames_in
    assert sock_sent == [bytes(m.data) for m in sent]
    log = tmp_path / "drive.log"
    with can.Logger(str(log)) as logger:
        for m in claimed:
            logger.on_message_received(m)
    out = tmp_path / "z.csv"
    assert main(["apply", str(tmp_path / "imu-z.yaml"), str(log), "--config", str(cfg), "-o", str(out)]) == 0
    assert len([r for r in out.read_text().splitlines() if not r.startswith("#")]) == len(claimed) + 1


def test_apply_with_dbc_and_j1939_message_reads_a_bare_dbcs_group(tmp_path: Path, capsys) -> None:
    """Without a configuration: --dbc, --j1939-message, --j1939-source and --input raw=."""
    from canical.commands.cli import main

    claimed = [m for m in re_addressed(vendor_stream(MESSAGE, 120)) if m.arbitration_id & 0xFF == 0x80]
    log = tmp_path / "drive.log"
    with can.Logger(str(log)) as logger:
        for m in claimed:
            logger.on_message_received(m)
    sets = write_sets(tmp_path, terms={"x": (), "y": (), "z": ()}, raw_units="deg/s")
    by_hand = ["--dbc", str(bare_dbc(tmp_path)), "--input", "raw=ANGRATE.YawRate", "--j1939-source", "0x80"]
    out = tmp_path / "z.csv"
    assert main(["apply", str(sets["z"]), str(log), *by_hand, "-o", str(out)]) == 2
    assert "no ANGRATE frames" in capsys.readouterr().err
    assert main(["apply", str(sets["z"]), str(log), *by_hand, "--j1939-message", "ANGRATE",
                 "-o", str(out)]) == 0, capsys.readouterr().err
    assert len([r for r in out.read_text().splitlines() if not r.startswith("#")]) == len(claimed) + 1


@pytest.mark.parametrize(("messages", "words"), [
    (["NOPE"], "j1939.messages: no message NOPE in vendor_bare.dbc"),
    ([], "j1939.messages: must be a list of message names or 'all'"),
    ("ANGRATE", "j1939.messages: must be a list of message names or 'all'"),
])
def test_a_bad_j1939_messages_key_is_one_line(tmp_path: Path, messages, words: str) -> None:
    with pytest.raises(CanicalError) as info:
        load_config(config_file(tmp_path, dbc=str(bare_dbc(tmp_path)),
                                j1939={"source_address": 0x80, "messages": messages}))
    assert words in str(info.value) and "\n" not in str(info.value)


@pytest.mark.parametrize(("source", "expected_sources"), [(None, {0x10}), ("any", {0x10, 0x80})])
def test_record_keeps_the_group_from_the_sources_it_is_told(tmp_path: Path, capsys, source,
                                                            expected_sources: set[int]) -> None:
    import threading
    import time
    import uuid

    from canical.commands.cli import main

    channel = f"j1939-{uuid.uuid4().hex}"
    msgs = re_addressed(vendor_stream(MESSAGE, 60))
    out = tmp_path / "rec.log"
    args = ["record", "--config", str(config_file(tmp_path)), "--channel", channel, "--duration", "1.5",
            "-o", str(out), *(["--j1939-source", source] if source else [])]

    def send() -> None:
        time.sleep(0.5)
        with can.Bus(interface="virtual", channel=channel) as bus:
            for m in msgs:
                bus.send(m)

    sender = threading.Thread(target=send)
    sender.start()
    try:
        assert main(args) == 0, capsys.readouterr().err
    finally:
        sender.join()
    got = list(can.LogReader(str(out)))
    assert {m.arbitration_id & 0xFF for m in got} == expected_sources
    assert len(got) == sum(m.arbitration_id & 0xFF in expected_sources for m in msgs)


@pytest.mark.vcan
def test_serve_on_vcan_corrects_the_group_from_any_source_and_nothing_else(vcan_channel: str,
                                                                          tmp_path: Path) -> None:
    """The kernel's receive filter is the group's mask: every frame of PGN 0xFF2A is corrected,
    whatever its priority and source, and a frame of the next group is not."""
    import subprocess
    import sys
    import time

    from support.daemon_fixtures import DaemonProcess, Recorder

    from canical.sessions.csv_file import read_table

    path = config_file(tmp_path, j1939={"source_address": "any"})
    content = yaml.safe_load(path.read_text())
    content["bus"] = {"interface": "socketcan", "channel": vcan_channel}
    path.write_text(yaml.safe_dump(content, sort_keys=False))
    msgs = re_addressed(vendor_stream(MESSAGE, 200))
    other_group = [can.Message(arbitration_id=0x18FF2B80, is_extended_id=True, data=bytes(8))] * 20
    rec = Recorder(vcan_channel)
    daemon = DaemonProcess(path)
    try:
        with can.Bus(interface="socketcan", channel=vcan_channel) as tx:
            for i, m in enumerate([*other_group, *msgs]):
                tx.send(can.Message(arbitration_id=m.arbitration_id, is_extended_id=True, data=bytes(m.data)),
                        timeout=1.0)
                if i % 8 == 7:
                    time.sleep(0.02)
        out = rec.wait_count(0x110, len(msgs), timeout=60)
        time.sleep(0.3)
    finally:
        code = daemon.stop()
        seen = list(rec.messages)
        rec.close()
    assert code == 0, daemon.log()
    assert len(out) == len(msgs), daemon.log()
    log = tmp_path / "bus.log"
    with can.Logger(str(log)) as logger:
        for m in seen:
            if m.arbitration_id not in (0x110, 0x111):
                logger.on_message_received(m)
    csv = tmp_path / "z.csv"
    proc = subprocess.run([sys.executable, "-m", "canical", "apply", str(tmp_path / "imu-z.yaml"), str(log),
                           "--config", str(path), "-o", str(csv)], capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    db = cantools.database.load_file(str(Path(__file__).resolve().parents[2] / "dbc" / "canical.dbc"))
    sent = np.array([db.get_message_by_name("CANICAL_RATE").decode(bytes(m.data))["RateZ"] for m in out])
    expected = np.clip(read_table(csv).columns["rate_dps"], -327.68, 327.67)
    assert np.max(np.abs(sent - expected)) <= 0.006
