"""A vendor-like IMU corrected by ``canical serve`` into its own layout, gateway vcan0 -> vcan1.

The IMU (tests/data: standard id Intel, and extended id Motorola with its temperature in a frame
of its own; no counter) sends its raw frames on vcan0; the daemon sends each corrected frame in
the IMU's own layout on vcan1. Every corrected frame, decoded with cantools, equals ``canical
apply`` on the same raw frames (to the signal's 0.1 deg/s, every other signal as it came), and
nothing sent on vcan1 ever appears on vcan0.
"""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import can
import numpy as np
import pytest
import yaml
from support.daemon_fixtures import DaemonProcess, Recorder
from test_daemon_own_layout import CASES, temp_frames, vendor_setup, vendor_stream

from canical.sessions.csv_file import read_table

pytestmark = pytest.mark.vcan

N = 300
RATE_HZ = 300.0
NOISE_ID = 0x7AB
MARK = b"\xee"


def _send(bus: can.BusABC, msgs: list[can.Message], rate_hz: float) -> None:
    start = time.monotonic()
    for i, m in enumerate(msgs):
        bus.send(can.Message(arbitration_id=m.arbitration_id, is_extended_id=m.is_extended_id,
                             data=bytes(m.data)), timeout=1.0)
        if i % 8 == 7:
            lag = start + (i + 1) / rate_hz - time.monotonic()
            if lag > 0:
                time.sleep(lag)


@pytest.mark.parametrize("case", sorted(CASES))
def test_vendor_imu_corrected_into_its_own_layout_through_a_one_way_gateway(
        vcan_channels: tuple[str, str], tmp_path: Path, case: str) -> None:
    sensor_bus, vehicle_bus = vcan_channels
    path, message = vendor_setup(tmp_path, case, channel=vehicle_bus)
    content = yaml.safe_load(path.read_text())
    content["bus"] = {"interface": "socketcan", "channel": sensor_bus}
    path.write_text(yaml.safe_dump(content, sort_keys=False))
    own_id = CASES[case][4]
    raws = vendor_stream(message, N)
    msgs = sorted([*raws, *(temp_frames(N) if CASES[case][3] else [])], key=lambda m: m.timestamp)

    rec_in, rec_out = Recorder(sensor_bus), Recorder(vehicle_bus)
    daemon = DaemonProcess(path)
    try:
        with can.Bus(interface="socketcan", channel=sensor_bus) as tx, \
                can.Bus(interface="socketcan", channel=vehicle_bus) as other:
            # Traffic of the vehicle's bus: the raw frame's own id, and another, with a marker.
            ids = ((message.frame_id, message.is_extended_frame), (NOISE_ID, False))
            noise = [can.Message(arbitration_id=fid, is_extended_id=ext, data=MARK * message.length)
                     for fid, ext in ids for _ in range(20)]
            _send(other, noise, RATE_HZ)
            _send(tx, msgs, RATE_HZ)
        out = rec_out.wait_count(own_id, N, timeout=60)
        time.sleep(0.5)
    finally:
        code = daemon.stop()
        seen_in, seen_out = list(rec_in.messages), list(rec_out.messages)
        rec_in.close()
        rec_out.close()
    assert code == 0, daemon.log()
    assert len(out) == N, daemon.log()
    assert all(m.is_extended_id == message.is_extended_frame and len(m.data) == message.length for m in out)

    # One way: nothing sent on the vehicle's bus reaches the sensor's, not even the corrected frames.
    marked = MARK * message.length
    assert not [m for m in seen_in if m.arbitration_id in (NOISE_ID, own_id) or bytes(m.data) == marked]
    assert not [m for m in seen_out if m.arbitration_id == 0x110]  # CANICAL_RATE stays on the sensor's bus

    # The same raw frames, as the sensor's bus carried them, through canical apply.
    log = tmp_path / "drive.log"
    with can.Logger(str(log)) as logger:
        for m in seen_in:
            if m.arbitration_id != 0x110 and m.arbitration_id != 0x111:
                logger.on_message_received(m)
    got = [message.decode(bytes(m.data), decode_choices=False) for m in out]
    came = [message.decode(bytes(m.data), decode_choices=False) for m in raws]
    signals = dict(zip("xyz", CASES[case][2], strict=True))
    for sig in message.signals:
        if sig.name not in signals.values():
            assert [g[sig.name] for g in got] == [c[sig.name] for c in came], sig.name
    for axis, name in signals.items():
        csv = tmp_path / f"apply-{axis}.csv"
        cset = tmp_path / f"imu-{axis}.yaml"
        proc = subprocess.run([sys.executable, "-m", "canical", "apply", str(cset), str(log),
                               "--config", str(path), "-o", str(csv)], capture_output=True, text=True)
        assert proc.returncode == 0, proc.stderr
        table = read_table(csv).columns
        assert len(table["rate_dps"]) == N
        expected = np.clip(table["rate_dps"], -3276.8, 3276.7)
        sent = np.array([g[name] for g in got])
        assert np.max(np.abs(sent - expected)) <= 0.05 + 1e-6, axis
