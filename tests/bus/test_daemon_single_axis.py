"""A single-axis yaw-rate sensor (issue 33, point 5): one axis named in ``axes:``, the others absent.

Many vehicle yaw-rate sensors have one axis. Its configuration names that axis alone; the
other two are never read (their canical default signal names are not in the vendor's message)
and go out uncalibrated. The sensor is simulated, calibrated and applied from CAN logs in the
vendor's layout, checked with ``serve --check`` and served in-process: the daemon's corrected
frames carry what ``apply`` gives for the same raw frames.
"""

from __future__ import annotations

import itertools
from pathlib import Path

import can
import cantools
import numpy as np
import pytest
import yaml
from test_daemon_compiled import StandInSocket, feed, handler_source, kernel_frame, serve_socket

from canical.bus.daemon import Daemon
from canical.bus.daemon_config import load_config
from canical.commands.cli import main
from canical.errors import CanicalError
from canical.sessions.csv_file import read_table

DATA = Path(__file__).resolve().parents[1] / "data"
VENDOR, VENDOR_EXT = DATA / "vendor_imu.dbc", DATA / "vendor_imu_ext.dbc"


def yaw_config(folder: Path, **extra) -> Path:
    content = {
        "bus": {"interface": "virtual", "channel": "yaw"},
        "dbc": [str(VENDOR), str(VENDOR_EXT)],
        "axes": {"z": {"raw": "GYRO_TPDO2.GyroZ", "coefficients": str(folder / "imu-z.yaml")}},
        "inputs": {"temp_c": {"signal": "IMU_TEMP.SensorTemp", "max_age_s": 1.0}},
        **extra,
    }
    path = folder / "yaw.yaml"
    path.write_text(yaml.safe_dump(content, sort_keys=False))
    return path


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory) -> Path:
    """A simulated yaw-rate sensor's session, calibrated with the one-axis configuration."""
    folder = tmp_path_factory.mktemp("yaw")
    config = yaw_config(folder)
    log = folder / "turntable.log"
    assert main(["simulate", "session", "--config", str(config), "-o", str(log)]) == 0
    assert main(["calibrate", str(log), "--config", str(config), "--sensor", "SIM-0001",
                 "-o", str(folder / "imu-z.yaml")]) == 0
    return config


def test_one_axis_is_configured_and_the_others_are_absent(calibrated: Path, capsys) -> None:
    config = load_config(calibrated)
    assert [a.present for a in config.axes] == [False, False, True]
    assert config.raw_message == "GYRO_TPDO2" and config.axes[2].raw_signal == "GyroZ"
    capsys.readouterr()
    assert main(["serve", "--config", str(calibrated), "--check"]) == 0
    out = capsys.readouterr().out
    assert "axis x: not in axes (absent: not read, not corrected)" in out
    assert "axis y: not in axes" in out and "axis z: set 0x" in out
    assert "corrected: axis z; not corrected: x, y\n" in out and "configuration OK (virtual yaw)" in out


def test_the_calibrated_axis_is_applied_and_served_as_apply_gives(calibrated: Path, tmp_path: Path,
                                                                  capsys) -> None:
    drive, out = tmp_path / "drive.log", tmp_path / "corrected.csv"
    assert main(["simulate", "drive", "--config", str(calibrated), "-o", str(drive)]) == 0
    assert main(["apply", str(calibrated.parent / "imu-z.yaml"), str(drive), "--config", str(calibrated),
                 "-o", str(out)]) == 0, capsys.readouterr().err
    applied = read_table(out).columns["rate_dps"]
    db = cantools.database.load_file(str(VENDOR), strict=False)
    raw_id = db.get_message_by_name("GYRO_TPDO2").frame_id
    frames = list(itertools.islice(can.LogReader(str(drive)), 20_000))  # the drive's first minutes
    config = load_config(calibrated)
    sent: list[can.Message] = []

    class RefBus:
        def send(self, msg: can.Message, timeout: float | None = None) -> None:
            sent.append(msg)

    reference, compiled = Daemon(config, compiled=False), Daemon(config)
    for daemon in (reference, compiled):
        daemon.load_sets()
    feed(reference, frames, RefBus())
    sock = StandInSocket(compiled, [(kernel_frame(m), m.timestamp) for m in frames])
    serve_socket(compiled, sock)
    n_raw = sum(1 for m in frames if m.arbitration_id == raw_id and not m.is_extended_id)
    assert reference.stats.frames_in == n_raw == len(sent) and len(applied) > n_raw
    assert sock.sent == [bytes(m.data) for m in sent]
    rate = cantools.database.load_file(str(Path(__file__).resolve().parents[2] / "dbc" / "canical.dbc"))
    decoded = [rate.decode_message("CANICAL_RATE", bytes(m.data)) for m in sent]
    assert all(d["UncalibratedX"] and d["UncalibratedY"] and d["RateX"] == 0 for d in decoded)
    calibrated_z = [(d["RateZ"], a) for d, a in zip(decoded, applied[:n_raw], strict=True)
                    if not d["UncalibratedZ"]]
    assert len(calibrated_z) > 0.9 * n_raw  # only frames before the first temperature are not
    served, expected = np.array(calibrated_z).T
    assert np.max(np.abs(served - expected)) <= 0.005 + 1e-9  # RateZ's 0.01 deg/s resolution
    assert "send" in handler_source(compiled)  # the generated handler served them


def test_an_imu_set_needs_every_axis(calibrated: Path, tmp_path: Path) -> None:
    path = yaw_config(tmp_path, imu_set=str(tmp_path / "imu.yaml"),
                      axes={"z": {"raw": "GYRO_TPDO2.GyroZ"}})
    with pytest.raises(CanicalError, match=r"axes.x: left out, but imu_set corrects x, y and z"):
        load_config(path)


def test_a_rate_frame_of_the_users_own_needs_only_the_named_axis(calibrated: Path, tmp_path: Path) -> None:
    """frames.rate may be a yaw-rate frame with the z signals alone: an absent axis needs none."""
    out_dbc = tmp_path / "yaw_out.dbc"
    out_dbc.write_text('VERSION ""\n\nNS_ :\n\nBS_:\n\nBU_: CANICAL\n\n'
                       'BO_ 784 YAW_OUT: 4 CANICAL\n'
                       ' SG_ RateZ : 0|16@1- (0.01,0) [-327.68|327.67] "deg/s" Vector__XXX\n'
                       ' SG_ OutOfSpanZ : 16|1@1+ (1,0) [0|1] "" Vector__XXX\n'
                       ' SG_ UncalibratedZ : 17|1@1+ (1,0) [0|1] "" Vector__XXX\n'
                       ' SG_ Stale : 18|1@1+ (1,0) [0|1] "" Vector__XXX\n'
                       ' SG_ CounterGap : 19|1@1+ (1,0) [0|1] "" Vector__XXX\n'
                       ' SG_ SetTag : 20|4@1+ (1,0) [0|15] "" Vector__XXX\n'
                       ' SG_ Counter : 24|4@1+ (1,0) [0|15] "" Vector__XXX\n')
    config_path = yaw_config(tmp_path, dbc=[str(VENDOR), str(VENDOR_EXT), str(out_dbc)],
                             frames={"rate": "YAW_OUT"},
                             axes={"z": {"raw": "GYRO_TPDO2.GyroZ",
                                         "coefficients": str(calibrated.parent / "imu-z.yaml")}})
    config = load_config(config_path)
    assert config.rate_message == "YAW_OUT"
    raw = cantools.database.load_file(str(VENDOR), strict=False).get_message_by_name("GYRO_TPDO2")
    temp = cantools.database.load_file(str(VENDOR_EXT), strict=False).get_message_by_name("IMU_TEMP")
    frames = []
    for i in range(50):
        frames.append(can.Message(timestamp=1.0 + 0.01 * i, arbitration_id=temp.frame_id, is_extended_id=True,
                                  data=temp.encode({"SensorTemp": 25.0})))
        rates = raw.encode({"GyroX": 0, "GyroY": 0, "GyroZ": 10.0})
        frames.append(can.Message(timestamp=1.0 + 0.01 * i + 1e-4, arbitration_id=raw.frame_id,
                                  is_extended_id=False, data=rates))
    sent: list[can.Message] = []

    class RefBus:
        def send(self, msg: can.Message, timeout: float | None = None) -> None:
            sent.append(msg)

    daemon = Daemon(config, compiled=False)
    daemon.load_sets()
    feed(daemon, frames, RefBus())
    out = cantools.database.load_file(str(out_dbc)).get_message_by_name("YAW_OUT")
    decoded = [out.decode(bytes(m.data)) for m in sent if m.arbitration_id == out.frame_id]
    assert len(decoded) == 50 and not decoded[-1]["UncalibratedZ"]
    assert abs(decoded[-1]["RateZ"] - 10.0) < 1.0
