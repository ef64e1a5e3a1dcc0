"""``canical serve`` as a separate process on a real SocketCAN vcan, as systemd would run it.

Each test starts the daemon from the deployable example configuration, with a notify socket
and a watchdog, streams a simulated IMU onto the bus and checks what comes back frame by
frame. Streams are paced for the slow one-CPU guest these run in on kernels without vcan.
"""

from __future__ import annotations

import json
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
from support.daemon_fixtures import (
    DBC,
    DaemonProcess,
    Recorder,
    decode_stream,
    expected_rates,
    imu_stream,
    send_paced,
    write_config,
    write_sets,
)
from support.systemd_guest import wait_until

from canical.files.atomic_file import write_text_atomic
from canical.frames.codec import load_dbc
from canical.sessions.csv_file import read_table

pytestmark = pytest.mark.vcan

RATE_HZ = 400.0  # raw frames per second sent; the guest manages several times that
HALF_LSB = 0.005 + 1e-9


@pytest.fixture(scope="module")
def db():
    return load_dbc(DBC)


def _bus(channel: str):
    import can

    return can.Bus(interface="socketcan", channel=channel)


def _rates(db, msgs) -> list[dict]:
    m = db.get_message_by_name("CANICAL_RATE")
    return [m.decode(bytes(x.data), decode_choices=False) for x in msgs]


def _status(db, msgs) -> dict[tuple[int, int], dict]:
    """Latest status page content by (page, axis)."""
    m = db.get_message_by_name("CANICAL_STATUS")
    out: dict[tuple[int, int], dict] = {}
    for x in msgs:
        d = m.decode(bytes(x.data), decode_choices=False)
        out[(d["Page"], d.get("SetAxis", 0))] = d
    return out


def _wait_status(db, rec: Recorder, pred, timeout: float = 10.0) -> dict:
    status_id = db.get_message_by_name("CANICAL_STATUS").frame_id
    end = time.monotonic() + timeout
    while True:
        st = _status(db, rec.of(status_id))
        if pred(st) or time.monotonic() > end:
            return st
        time.sleep(0.1)


def _set_mtu(channel: str, mtu: int) -> None:
    for args in (("down",), ("mtu", str(mtu)), ("up",)):
        subprocess.run(["ip", "link", "set", channel, *args], check=True)


def _write_canlog(path: Path, msgs) -> None:
    import can

    with can.Logger(str(path)) as logger:
        for m in msgs:
            logger.on_message_received(m)


def test_daemon_corrects_stream_like_apply(vcan_channel: str, tmp_path: Path, db) -> None:
    """Every raw frame gets one corrected frame equal (to the 0.01 deg/s resolution) to what
    ``canical apply`` computes from a candump log of the same frames; systemd hears READY,
    WATCHDOG and STATUS; SIGTERM stops it cleanly with a last status frame."""
    paths = write_sets(tmp_path)
    config = write_config(tmp_path, vcan_channel)
    stream = imu_stream(1200)
    rec = Recorder(vcan_channel)
    daemon = DaemonProcess(config)
    try:
        assert "running" in daemon.ready["STATUS"]
        with _bus(vcan_channel) as tx:
            send_paced(tx, stream.frames, RATE_HZ * 1.1)
        rate_id = db.get_message_by_name("CANICAL_RATE").frame_id
        out = rec.wait_count(rate_id, len(stream.raw_index), timeout=30)
        daemon.notify.wait_for("WATCHDOG", 5)
        time.sleep(1.5)  # one more status period
        assert daemon.notify.count("WATCHDOG") >= 2
        assert any("1200 frames in" in m.get("STATUS", "") for m in daemon.notify.messages)
    finally:
        code = daemon.stop()
        rec_msgs = list(rec.messages)
        rec.close()
    assert code == 0, daemon.log()
    assert daemon.notify.count("STOPPING") == 1
    assert len(out) == len(stream.raw_index), daemon.log()

    # The same frames as the bus carried them, through canical apply.
    log = tmp_path / "drive.log"
    _write_canlog(log, [m for m in rec_msgs if m.arbitration_id in (0x190, 0x290)])
    got = _rates(db, out)
    assert [g["Counter"] for g in got] == [i & 0xF for i in range(len(got))]
    assert not any(g["CounterGap"] or g["Stale"] for g in got)
    for axis in ("x", "y", "z"):
        csv = tmp_path / f"apply-{axis}.csv"
        proc = subprocess.run([sys.executable, "-m", "canical", "apply", str(paths[axis]), str(log),
                               "--config", str(config), "-o", str(csv)], capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr
        table = read_table(csv).columns
        assert len(table["rate_dps"]) == len(got)
        expected = np.clip(table["rate_dps"], -327.68, 327.67)
        sent = np.array([g[f"Rate{axis.upper()}"] for g in got])
        assert np.max(np.abs(sent - expected)) <= HALF_LSB, axis
        assert [g[f"OutOfSpan{axis.upper()}"] for g in got] == table["out_of_span"].astype(int).tolist()
        assert not any(g[f"Uncalibrated{axis.upper()}"] for g in got)
        assert table["out_of_span"].any() and not table["out_of_span"].all()  # both kinds exercised

    status_id = db.get_message_by_name("CANICAL_STATUS").frame_id
    st = _status(db, [m for m in rec_msgs if m.arbitration_id == status_id])
    assert st[(0, 0)]["State"] == 3  # the last status frame says "stopping"
    assert st[(0, 0)]["FramesIn"] == st[(0, 0)]["FramesOut"] == len(got)
    assert st[(0, 0)]["FramesBad"] == 0
    for code_axis in range(3):
        assert st[(1, code_axis)]["SetId"] != 0 and st[(1, code_axis)]["SetSource"] == 1


def test_hot_reload_while_streaming(vcan_channel: str, tmp_path: Path, db) -> None:
    """Sets replaced by SIGHUP and by a file change mid-stream: no frame lost, every frame
    corrected wholly by one generation (all three axes), generations in order; a damaged set
    is refused and the running one stays."""
    gens = []
    for variant in (0, 1, 2):
        folder = tmp_path / f"g{variant}"
        folder.mkdir()
        gens.append(write_sets(folder, variant=variant))
    live = tmp_path / "live"
    live.mkdir()
    live_paths = {a: live / f"imu-{a}.yaml" for a in ("x", "y", "z")}
    for axis, path in live_paths.items():
        write_text_atomic(path, gens[0][axis].read_text())
    config = write_config(live, vcan_channel, watch_period_s=0.2)
    stream = imu_stream(2400, seed=5)
    rec = Recorder(vcan_channel)
    daemon = DaemonProcess(config)
    thirds = [stream.raw_index[i] for i in (800, 1600)]
    try:
        with _bus(vcan_channel) as tx:
            send_paced(tx, stream.frames[: thirds[0]], RATE_HZ)
            for axis, path in live_paths.items():  # generation 1, announced by SIGHUP
                write_text_atomic(path, gens[1][axis].read_text())
            hup_at = time.time()  # the clock of the frames' kernel timestamps
            daemon.signal(signal.SIGHUP)
            send_paced(tx, stream.frames[thirds[0] : thirds[1]], RATE_HZ)
            write_text_atomic(live_paths["z"], "schema: 1\ncrc32: '0x0'\n")  # damaged: refused
            time.sleep(0.5)
            for axis in ("x", "y"):  # generation 2, noticed by the file watch alone
                write_text_atomic(live_paths[axis], gens[2][axis].read_text())
            send_paced(tx, stream.frames[thirds[1] :], RATE_HZ)
        rate_id = db.get_message_by_name("CANICAL_RATE").frame_id
        out = rec.wait_count(rate_id, len(stream.raw_index), timeout=30)
    finally:
        code = daemon.stop()
        rec.close()
    assert code == 0
    log = daemon.log()
    assert len(out) == len(stream.raw_index), log
    got = _rates(db, out)
    assert [g["Counter"] for g in got] == [i & 0xF for i in range(len(got))]
    assert "axis z:" in log and "keeping set" in log

    # Which generation corrected each frame, told by the x axis (its terms have no state, so each
    # generation's rate is known for every frame; generations differ there by 0.1 deg/s, far
    # above the resolution): they must follow in order.
    signals = decode_stream(stream)
    x_rates = {g["x"]: expected_rates(signals, {**gens[0], "x": g["x"]})["x"] for g in gens}
    mixed = {"z": gens[1]["z"], "x": gens[2]["x"], "y": gens[2]["y"]}
    sent = {axis: np.array([g[f"Rate{axis.upper()}"] for g in got]) for axis in ("x", "y", "z")}
    labels = []
    for i in range(len(got)):
        fits = [k for k, paths in enumerate((gens[0], gens[1], mixed))
                if abs(sent["x"][i] - x_rates[paths["x"]][i]) <= HALF_LSB]
        assert len(fits) == 1, (i, fits, log)
        labels.append(fits[0])
    assert labels == sorted(labels) and set(labels) == {0, 1, 2}, log
    a, b = labels.index(1), labels.index(2)
    late_s = out[a].timestamp - hup_at  # from SIGHUP to the first frame of the new sets
    print(f"reload adopted {a - 800} frames, {late_s * 1e3:.0f} ms after SIGHUP; file change at frame {b}")
    print("\n".join(line for line in log.splitlines() if "reload (" in line))
    # Then every frame, all three axes at once, must be exactly that generation's: a new set
    # starts its own direction state at the frame it was adopted (y's direction term), a kept
    # one (z in generation 2) carries on. A frame corrected with a mix of two generations, or
    # with the state of an older corrector, would be 0.1 deg/s off on some axis.
    expected = expected_rates(signals, gens[0], switches=((a, gens[1]), (b, mixed)))
    for axis in ("x", "y", "z"):
        off = np.flatnonzero(np.abs(sent[axis] - expected[axis]) > HALF_LSB)
        assert off.size == 0, (axis, off[:10], a, b, log)
    # The reload landed where asked. The daemon's part: adopt the new sets as soon as the worker
    # has built them (the next periodic step: RELOAD_POLL_S plus at most one burst), and switch
    # at the frame it is handling then. The build itself (YAML, validation: ~40 ms CPU in an idle
    # guest) runs beside the frames; in the one-CPU guest it shares with this test's sender and
    # recorder on a busy host it took 140-300 ms of wall time in the runs that failed a fixed
    # "50 frames after SIGHUP" (137 ms): that bound measured the machine's load, not the daemon.
    reloads = re.findall(r"reload \((SIGHUP|file changed)\): built in (\d+) ms \(\d+ ms CPU\), "
                         r"adopted (\d+) ms", log)
    assert [why for why, _, _ in reloads] == ["SIGHUP", "file changed", "file changed"], log
    for _, built_ms, adopted_ms in reloads:
        assert int(adopted_ms) - int(built_ms) <= 50 and int(built_ms) <= 2000, reloads
    raw_hz = RATE_HZ * 10 / 11  # an aux frame before every 10th raw frame
    hup_s, watch_s = int(reloads[0][2]) / 1e3, 0.2 + int(reloads[2][2]) / 1e3  # generation 2: file watch
    assert 0 < a <= 800 + raw_hz * (hup_s + 0.05), (a, late_s, reloads)
    assert 1600 <= b <= 1600 + raw_hz * (watch_s + 0.05), (b, reloads)
    tags = [g["SetTag"] for g in got]
    for start, stop in ((0, a), (a, b), (b, len(got))):
        assert len(set(tags[start:stop])) == 1


def test_faults_counted_and_ignored(vcan_channel: str, tmp_path: Path, db) -> None:
    """Wrong length, unknown ids, error, remote and CAN FD frames are counted and dropped;
    a counter jump sets CounterGap; a missing input sets Stale; good frames still flow."""
    import can

    _set_mtu(vcan_channel, 72)  # let CAN FD frames through
    write_sets(tmp_path)
    config = write_config(tmp_path, vcan_channel)
    text = config.read_text().replace("max_age_s: 2.0", "max_age_s: 0.3")
    config.write_text(text)
    stream = imu_stream(40)
    raw = [f for f in stream.frames if f[0] == 0x190]
    aux = [f for f in stream.frames if f[0] == 0x290]
    rec = Recorder(vcan_channel)
    daemon = DaemonProcess(config)
    try:
        with _bus(vcan_channel) as tx, can.Bus(interface="socketcan", channel=vcan_channel, fd=True) as fd:
            def send(**kw) -> None:
                tx.send(can.Message(is_extended_id=kw.pop("is_extended_id", False), **kw))

            send(arbitration_id=0x290, data=aux[0][1])
            for fid, data in raw[:10]:
                send(arbitration_id=fid, data=data)
            send(arbitration_id=0x190, data=raw[10][1][:6])  # wrong length
            send(arbitration_id=0x290, data=aux[1][1][:4])  # wrong length, input frame
            send(arbitration_id=0x190, is_remote_frame=True, dlc=8)
            send(arbitration_id=0x123, data=b"\1\2\3\4\5\6\7\x08")  # unknown ids
            send(arbitration_id=0x190, is_extended_id=True, data=raw[10][1])
            send(arbitration_id=0x004, is_error_frame=True, data=bytes(8))
            fd.send(can.Message(arbitration_id=0x190, is_extended_id=False, is_fd=True,
                                data=raw[10][1] + bytes(4)))
            for fid, data in raw[12:20]:  # counter skips 10 and 11: one gap
                send(arbitration_id=fid, data=data)
            time.sleep(0.6)  # Uptime (IMU_AUX) now older than its 0.3 s
            for fid, data in raw[20:25]:
                send(arbitration_id=fid, data=data)
        rate_id = db.get_message_by_name("CANICAL_RATE").frame_id
        out = rec.wait_count(rate_id, 23, timeout=20)
        time.sleep(0.3)
        st = _wait_status(db, rec, lambda s: s.get((2, 0), {}).get("FdFrames", 0) >= 1
                          and s.get((0, 0), {}).get("FramesIn", 0) >= 23)
    finally:
        code = daemon.stop()
        rec.close()
        _set_mtu(vcan_channel, 16)
    assert code == 0
    got = _rates(db, out)
    assert len(got) == 23, daemon.log()  # 10 + 8 + 5 good raw frames, nothing else
    assert [g["CounterGap"] for g in got] == [0] * 10 + [1] + [0] * 12
    assert [g["Stale"] for g in got] == [0] * 18 + [1] * 5
    assert not any(g["UncalibratedX"] or g["UncalibratedY"] or g["UncalibratedZ"] for g in got)
    page0, page2 = st[(0, 0)], st[(2, 0)]
    assert page0["FramesIn"] == 23 and page0["CounterGaps"] == 1 and page0["BusErrors"] == 1
    assert (page2["BadLength"], page2["RemoteFrames"], page2["FdFrames"]) == (2, 1, 1)
    assert page2["UnknownIds"] == 0  # the kernel's filters kept them from the daemon entirely
    assert page0["FramesBad"] == 4
    assert page2["StaleFrames"] == 5


def test_interface_down_and_up_survived(vcan_channel: str, tmp_path: Path, db) -> None:
    """ip link down/up under a running daemon: it reopens the interface and corrects again."""
    write_sets(tmp_path)
    config = write_config(tmp_path, vcan_channel)
    stream = imu_stream(400)
    half = stream.raw_index[200]
    rec = Recorder(vcan_channel)
    daemon = DaemonProcess(config)
    rate_id = db.get_message_by_name("CANICAL_RATE").frame_id
    try:
        with _bus(vcan_channel) as tx:
            send_paced(tx, stream.frames[:half], RATE_HZ)
        assert len(rec.wait_count(rate_id, 200, timeout=20)) == 200
        subprocess.run(["ip", "link", "set", vcan_channel, "down"], check=True)
        time.sleep(1.5)
        subprocess.run(["ip", "link", "set", vcan_channel, "up"], check=True)
        # frames sent before the reopen are not the daemon's to see; its back-off may take 2 s
        wait_until("the daemon to reopen the interface", lambda: "reopened" in daemon.log(), 20, 0.05)
        with _bus(vcan_channel) as tx:
            send_paced(tx, stream.frames[half:], RATE_HZ)
        out = rec.wait_count(rate_id, 400, timeout=20)
        st = _wait_status(db, rec, lambda s: s.get((2, 0), {}).get("BusRestarts", 0) >= 1)
        alive = daemon.proc.poll() is None
    finally:
        code = daemon.stop()
        rec.close()
    assert alive and code == 0, daemon.log()
    assert len(out) == 400, daemon.log()
    assert st[(2, 0)]["BusRestarts"] >= 1, (st, daemon.log())
    assert "reopened" in daemon.log()


def test_daemon_tracks_the_bias_like_apply(vcan_channel: str, tmp_path: Path, db) -> None:
    """bias_tracking: on: every corrected frame equals apply --track-bias's rate_dps - bias_dps (to
    the 0.01 deg/s resolution) on a candump log of the same frames: a standstill, a steady turn on
    z, a standstill. The daemon logs what it adopted and refused, and saves the learned state."""
    from test_daemon_bias_tracking import drive_frames

    from canical.tracking import state_file
    from canical.tracking.config import TrackerConfig

    paths = write_sets(tmp_path)
    config = write_config(tmp_path, vcan_channel,
                          bias_tracking={"enabled": True, "arw_deg_rt_h": 0.5, "state_file": "bias.json"})
    frames = [(m.arbitration_id, bytes(m.data)) for m in drive_frames(40.0)]
    raw_count = sum(1 for fid, _ in frames if fid == 0x190)
    rec = Recorder(vcan_channel)
    daemon = DaemonProcess(config)
    try:
        with _bus(vcan_channel) as tx:
            send_paced(tx, frames, RATE_HZ * 1.1)
        rate_id = db.get_message_by_name("CANICAL_RATE").frame_id
        out = rec.wait_count(rate_id, raw_count, timeout=60)
        time.sleep(1.5)  # one more status period: events logged, state saved
        assert any("z bias" in m.get("STATUS", "") for m in daemon.notify.messages)
    finally:
        code = daemon.stop()
        rec_msgs = list(rec.messages)
        rec.close()
    assert code == 0, daemon.log()
    assert len(out) == raw_count, daemon.log()
    # the steady 15 deg/s turn is driving: not a standstill, so not logged as one refused
    assert "adopted" in daemon.log() and "refused" not in daemon.log()
    log = tmp_path / "drive.log"
    _write_canlog(log, [m for m in rec_msgs if m.arbitration_id in (0x190, 0x290)])
    got = _rates(db, out)
    for axis in ("x", "y", "z"):
        csv = tmp_path / f"apply-{axis}.csv"
        proc = subprocess.run([sys.executable, "-m", "canical", "apply", str(paths[axis]), str(log),
                               "--config", str(config), "--track-bias", "-o", str(csv)],
                              capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr
        table = read_table(csv).columns
        assert len(table["rate_dps"]) == len(got)
        expected = np.clip(table["rate_dps"] - table["bias_dps"], -327.68, 327.67)
        sent = np.array([g[f"Rate{axis.upper()}"] for g in got])
        assert np.max(np.abs(sent - expected)) <= HALF_LSB + 2e-6, axis
    status = db.get_message_by_name("CANICAL_STATUS")
    pages = [status.decode(bytes(m.data), decode_choices=False) for m in rec_msgs
             if m.arbitration_id == status.frame_id]
    bias = {p["BiasAxis"]: p for p in pages if p["Page"] == 3}  # the last of each axis
    assert sorted(bias) == [0, 1, 2] and abs(bias[2]["BiasLearned"] - 0.3) < 0.05
    assert bias[2]["BiasUpdates"] > 10 and bias[2]["BiasAge"] < 65535
    text = (tmp_path / "bias.json").read_text()  # saved at stop, keyed by the sets' combined id
    learned = state_file.parse(text, int(json.loads(text)["set_id"], 16), ("x", "y", "z"),
                               state_file.StateLimits.of(TrackerConfig()))
    assert learned[2].updates > 10


def test_daemon_with_an_imu_set_corrects_like_apply(vcan_channel: str, tmp_path: Path, db) -> None:
    """imu_set: and bias_tracking: on a drive turning about three axes at once (a standstill, a
    steady turn about x, y and z together, a standstill): every corrected frame equals what
    ``apply imu.yaml LOG --config --track-bias`` computes from a candump log of the same frames
    (coupled rates less the one tracker's bias, to the 0.01 deg/s resolution), and the coupling
    is there to see (the per-axis rates differ from the coupled ones by far more)."""
    from support.daemon_fixtures import imu_set_config, write_imu_set
    from test_daemon_bias_tracking import drive_frames

    from canical.sets import coefficient_file, imu_set

    imu_path = write_imu_set(tmp_path)
    config = imu_set_config(tmp_path, vcan_channel,
                            bias_tracking={"enabled": True, "arw_deg_rt_h": 0.5, "state_file": "bias.json"})
    frames = [(m.arbitration_id, bytes(m.data)) for m in drive_frames(40.0, turns=(-12.0, 20.0, 15.0))]
    raw_count = sum(1 for fid, _ in frames if fid == 0x190)
    rec = Recorder(vcan_channel)
    daemon = DaemonProcess(config)
    try:
        with _bus(vcan_channel) as tx:
            send_paced(tx, frames, RATE_HZ * 1.1)
        out = rec.wait_count(db.get_message_by_name("CANICAL_RATE").frame_id, raw_count, timeout=60)
        time.sleep(1.5)  # one more status period: events logged, state saved
    finally:
        code = daemon.stop()
        rec_msgs = list(rec.messages)
        rec.close()
    assert code == 0, daemon.log()
    assert len(out) == raw_count, daemon.log()
    imu_id = imu_set.imu_set_crc(imu_set.load(imu_path))
    assert f"imu set {imu_id:08x}" in daemon.log() and "adopted" in daemon.log()
    log = tmp_path / "drive.log"
    _write_canlog(log, [m for m in rec_msgs if m.arbitration_id in (0x190, 0x290)])
    got = _rates(db, out)
    assert {g["SetTag"] for g in got} == {imu_id & 0xF}
    csv = tmp_path / "apply.csv"
    proc = subprocess.run([sys.executable, "-m", "canical", "apply", str(imu_path), str(log),
                           "--config", str(config), "--track-bias", "-o", str(csv)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    table = read_table(csv).columns
    plain = tmp_path / "plain.csv"  # without the coupling: each axis's own set
    for axis in ("x", "y", "z"):
        expected = np.clip(table[f"rate_{axis}_dps"] - table[f"bias_{axis}_dps"], -327.68, 327.67)
        sent = np.array([g[f"Rate{axis.upper()}"] for g in got])
        assert len(expected) == len(sent)
        assert np.max(np.abs(sent - expected)) <= HALF_LSB + 2e-6, axis
    imu = imu_set.load(imu_path)
    coefficient_file.save(tmp_path / "x-alone.yaml", imu.axes[0])
    proc = subprocess.run([sys.executable, "-m", "canical", "apply", str(tmp_path / "x-alone.yaml"),
                           str(log), "--config", str(config), "-o", str(plain)],
                          capture_output=True, text=True)
    assert proc.returncode == 0, proc.stderr
    per_axis = read_table(plain).columns["rate_dps"]
    sent_x = np.array([g["RateX"] for g in got])
    assert np.max(np.abs(sent_x - per_axis)) > 0.1  # 20 deg/s on y couples 0.24 deg/s into x
