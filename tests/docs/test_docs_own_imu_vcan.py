"""docs/own-imu.md §5 "on the vehicle": ``canical serve --config vendor.yaml`` on a live bus.

The one command of the page that ``test_docs_own_imu.py`` cannot run: it needs SocketCAN, so it
runs here in the vcan guest. The page's own ``vendor.yaml`` (its bus pointed at the guest's
vcan0), the set its §4 commands calibrate, frames of the vendor's layout in (``TPDO2_Gyro`` and
``TPDO3_Temp``, from the page's simulated drive): for every raw frame the daemon sends the
vendor's message again at the page's ``own_layout`` id, ``Gyr_Z`` corrected as ``canical apply``
corrects the same frames (to the signal's 0.1 deg/s), ``Gyr_X`` and ``Gyr_Y`` as they came.
"""

from __future__ import annotations

import shutil
import time
from pathlib import Path

import can
import cantools
import numpy as np
import pytest
import yaml
from support.daemon_fixtures import DaemonProcess, Recorder
from test_docs_own_imu import PAGE, ROOT, walkthrough_steps

from canical.commands.cli import main
from canical.sessions.csv_file import read_table

pytestmark = pytest.mark.vcan

N = 300  # raw frames sent
RATE_HZ = 300.0  # what the guest carries without loss (../shared/notes/vcan-here.md)
RAW_ID, TEMP_ID = 0x288, 0x388
#: The page's commands that make what serve needs: the session, its set, a drive to replay.
BEFORE_SERVE = (["simulate", "session", "--config", "vendor.yaml"], ["calibrate", "turntable.log"],
                ["simulate", "drive", "--config", "vendor.yaml"])


def page_setup(folder: Path, channel: str) -> dict:
    """vendor.yaml as the page writes it, on ``channel``; the page's §4 commands run before serve."""
    steps = walkthrough_steps(PAGE.read_text(encoding="utf-8"), whole=True)
    config = next(s.text for s in steps if s.file == "vendor.yaml")
    assert "channel: can0" in config
    on_vcan = config.replace("channel: can0", f"channel: {channel}")
    (folder / "vendor.yaml").write_text(on_vcan, encoding="utf-8")
    shutil.copy(ROOT / "tests" / "data" / "vendor_canopen_gyro.dbc", folder / "vendor.dbc")
    for prefix in BEFORE_SERVE:
        step = next(s for s in steps if s.argv[: len(prefix)] == prefix)
        assert main(step.argv) == 0, step.argv
    return yaml.safe_load(config)


def vendor_frames(drive: Path, db) -> list[can.Message]:
    """The drive's first N raw frames and the temperature frames among them; Gyr_X and Gyr_Y
    given values of their own, to see them copied through."""
    gyro = db.get_message_by_name("TPDO2_Gyro")
    out: list[can.Message] = []
    raws = 0
    for m in can.LogReader(str(drive)):
        if m.arbitration_id == RAW_ID:
            values = {**gyro.decode(bytes(m.data)), "Gyr_X": 0.1 * (raws % 97), "Gyr_Y": -0.1 * (raws % 41)}
            m = can.Message(arbitration_id=RAW_ID, is_extended_id=False, data=gyro.encode(values))
            raws += 1
        out.append(can.Message(arbitration_id=m.arbitration_id, is_extended_id=False, data=bytes(m.data)))
        if raws == N:
            return out
    raise AssertionError(f"the drive has only {raws} raw frames")


def send(bus: can.BusABC, msgs: list[can.Message]) -> None:
    start = time.monotonic()
    for i, m in enumerate(msgs):
        bus.send(m, timeout=1.0)
        lag = start + (i + 1) / RATE_HZ - time.monotonic()
        if lag > 0:
            time.sleep(lag)


def test_serve_on_the_vehicle_corrects_the_vendors_frames(vcan_channel: str, tmp_path: Path,
                                                         monkeypatch) -> None:
    monkeypatch.chdir(tmp_path)
    config = page_setup(tmp_path, vcan_channel)
    own_id = int(config["own_layout"]["id"])
    db = cantools.database.load_file(str(tmp_path / "vendor.dbc"))
    msgs = vendor_frames(tmp_path / "drive.log", db)

    recorder = Recorder(vcan_channel)
    daemon = DaemonProcess(tmp_path / "vendor.yaml")  # canical serve --config vendor.yaml
    try:
        with can.Bus(interface="socketcan", channel=vcan_channel) as imu:
            send(imu, msgs)
        out = recorder.wait_count(own_id, N, timeout=60)
        time.sleep(0.3)
    finally:
        code = daemon.stop()
        seen = list(recorder.messages)
        recorder.close()
    assert code == 0, daemon.log()
    assert len(out) == N, daemon.log()
    assert len([m for m in seen if m.arbitration_id == 0x110]) == N  # CANICAL_RATE beside it

    # The same raw frames, as the bus carried them, through canical apply.
    with can.Logger(str(tmp_path / "sent.log")) as logger:
        for m in seen:
            if m.arbitration_id in (RAW_ID, TEMP_ID):
                logger.on_message_received(m)
    assert main(["apply", "imu-z.yaml", "sent.log", "--config", "vendor.yaml", "-o", "applied.csv"]) == 0
    applied = read_table(tmp_path / "applied.csv").columns["rate_dps"]
    gyro = db.get_message_by_name("TPDO2_Gyro")
    got = [gyro.decode(bytes(m.data)) for m in out]
    came = [gyro.decode(bytes(m.data)) for m in msgs if m.arbitration_id == RAW_ID]
    assert [(g["Gyr_X"], g["Gyr_Y"]) for g in got] == [(c["Gyr_X"], c["Gyr_Y"]) for c in came]
    corrected = np.array([g["Gyr_Z"] for g in got])
    raw = np.array([c["Gyr_Z"] for c in came])
    assert len(applied) == N and np.max(np.abs(corrected - applied)) <= 0.05 + 1e-6
    assert np.max(np.abs(corrected - raw)) > 0.1  # the set did correct (bias 0.3 deg/s and more)
