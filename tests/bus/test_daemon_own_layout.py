"""The corrected frame in the IMU's own layout, in-process: a vendor's frame in, the same frame out.

A vendor-like IMU (tests/data: standard id Intel, extended id Motorola, no counter) goes through
the reference handler (python-can messages, cantools codecs) and the compiled one (generated
decode, correctors and encode on a stand-in raw socket). Both must send the same frames, each
the raw frame's message with the axes' signals replaced by their corrected values (saturated to
the signal's range, rounded by the encode) and every other signal as it came.
"""

from __future__ import annotations

from pathlib import Path

import can
import cantools
import numpy as np
import pytest
import yaml
from support.daemon_fixtures import TERMS, write_sets
from test_daemon_compiled import StandInSocket, feed, handler_source, kernel_frame, serve_socket

from canical.bus.daemon import Daemon
from canical.bus.daemon_config import load_config
from canical.errors import CanicalError

DATA = Path(__file__).resolve().parents[1] / "data"
VENDOR, VENDOR_EXT = DATA / "vendor_imu.dbc", DATA / "vendor_imu_ext.dbc"
CASES = {
    "intel-standard": (VENDOR, "GYRO_TPDO2", ("GyroX", "GyroY", "GyroZ"), None, 0x298),
    "motorola-extended": (VENDOR_EXT, "ANGRATE", ("RollRate", "PitchRate", "YawRate"), "IMU_TEMP.SensorTemp",
                          0x18FF2A20),
}


def vendor_setup(folder: Path, case: str, **own) -> tuple[Path, cantools.database.can.Message]:
    dbc, message, signals, temp, out_id = CASES[case]
    terms = {"x": TERMS["x"][:1] if temp else (), "y": (), "z": ()}
    sets = write_sets(folder, terms=terms, raw_units="deg/s")
    content = {
        "bus": {"interface": "virtual", "channel": "sensor"},
        "dbc": str(dbc),
        "axes": {a: {"raw": f"{message}.{s}", "coefficients": str(sets[a])}
                 for a, s in zip("xyz", signals, strict=True)},
        "inputs": {"temp_c": {"signal": temp, "max_age_s": 5.0}} if temp else {},
        "own_layout": {"id": out_id, **own},
    }
    path = folder / "vendor.yaml"
    path.write_text(yaml.safe_dump(content, sort_keys=False))
    db = cantools.database.load_file(str(dbc), strict=False)
    return path, db.get_message_by_name(message)


def vendor_stream(message, n: int, seed: int = 5) -> list[can.Message]:
    """Raw frames at rates up to past the signal's range (some saturate), the other signals random."""
    rng = np.random.default_rng(seed)
    msgs = []
    for i in range(n):
        values = {s.name: (float(np.round(rng.uniform(-400.0, 400.0), 1)) if s.unit == "deg/s"
                           else int(rng.integers(0, 1 << s.length)) if not s.is_signed else 0)
                  for s in message.signals}
        msgs.append(can.Message(arbitration_id=message.frame_id, is_extended_id=message.is_extended_frame,
                                data=message.encode(values), timestamp=10.0 + i * 0.005))
    return msgs


def temp_frames(n: int) -> list[can.Message]:
    msg = cantools.database.load_file(str(VENDOR_EXT), strict=False).get_message_by_name("IMU_TEMP")
    data = msg.encode({"SensorTemp": 31.5})
    return [can.Message(arbitration_id=msg.frame_id, is_extended_id=True, data=data,
                        timestamp=10.0 + i * 0.005 - 0.001) for i in range(n)]


@pytest.mark.parametrize("case", sorted(CASES))
def test_own_layout_frames_are_the_raw_frames_with_corrected_axes(tmp_path: Path, case: str) -> None:
    path, message = vendor_setup(tmp_path, case)
    config = load_config(path)
    raws = vendor_stream(message, 300)
    msgs = sorted([*raws, *(temp_frames(300) if CASES[case][3] else [])], key=lambda m: m.timestamp)
    reference, compiled = Daemon(config, compiled=False), Daemon(config)
    sent_ref: list[can.Message] = []

    class RefBus:
        def send(self, msg: can.Message, timeout: float | None = None) -> None:
            sent_ref.append(msg)

    for daemon in (reference, compiled):
        daemon.load_sets()
    feed(reference, msgs, RefBus())
    sock = StandInSocket(compiled, [(kernel_frame(m), m.timestamp) for m in msgs])
    serve_socket(compiled, sock)
    assert "send_own" in handler_source(compiled)  # the generated handler sent them

    own_id = CASES[case][4]
    own_ref = [bytes(m.data) for m in sent_ref if m.arbitration_id == own_id]
    assert len(own_ref) == 300 and all(m.is_extended_id == message.is_extended_frame
                                       for m in sent_ref if m.arbitration_id == own_id)
    assert sock.sent == [bytes(m.data) for m in sent_ref]  # the same frames, own layout and CANICAL_RATE

    axes = {s: a for a, s in zip("xyz", CASES[case][2], strict=True)}
    correctors = {ax.axis: ax.corrector for ax in reference.sets.axes}
    inputs = {"temp_c": 31.5} if CASES[case][3] else {}
    for raw, out in zip(raws, own_ref, strict=True):
        got, came = message.decode(out, decode_choices=False), message.decode(raw.data, decode_choices=False)
        for sig in message.signals:
            if sig.name not in axes:
                assert got[sig.name] == came[sig.name]
                continue
            rate, _ = correctors[axes[sig.name]].correct_one(came[sig.name], inputs)
            want = message.decode(message.encode({**came, sig.name: min(3276.7, max(-3276.8, rate))}),
                                  decode_choices=False)[sig.name]
            assert got[sig.name] == want


def test_gateway_sends_the_own_layout_on_the_output_bus_and_reads_nothing_from_it(tmp_path: Path) -> None:
    path, message = vendor_setup(tmp_path, "intel-standard", channel="vehicle")
    config = load_config(path)
    assert config.own_layout is not None and config.own_layout.channel == "vehicle"
    raws = vendor_stream(message, 50)
    daemon = Daemon(config)
    daemon.load_sets()
    sock = StandInSocket(daemon, [(kernel_frame(m), m.timestamp) for m in raws])
    out = StandInSocket(daemon, [])
    out.recvmsg = None  # type: ignore[assignment, method-assign]  # never read
    serve_socket(daemon, sock, out)
    # The own layout on the vehicle's bus, CANICAL_RATE on the sensor's.
    assert len(out.sent) == 50 and len(sock.sent) == 50
    assert all(len(p) == message.length for p in out.sent)


@pytest.mark.parametrize(
    ("own", "key"),
    [({"id": 0x288}, "own_layout.id"), ({"id": 0x110}, "own_layout.id"), ({"id": 0x800}, "own_layout.id"),
     ({"id": 0x298, "extended": "yes"}, "own_layout.extended"),
     ({"id": 0x298, "chanel": "x"}, "own_layout.chanel"),
     ({"id": 0x298, "channel": ""}, "own_layout.channel")],
)
def test_bad_own_layout_is_one_line_exit_2(tmp_path: Path, capsys, own, key) -> None:
    from canical.commands.cli import main

    path, _ = vendor_setup(tmp_path, "intel-standard")
    content = yaml.safe_load(path.read_text())
    content["own_layout"] = own
    path.write_text(yaml.safe_dump(content))
    assert main(["serve", "--config", str(path), "--check"]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and f"{path}: {key}: " in err[0], err


def test_own_layout_alone_without_canical_rate(tmp_path: Path) -> None:
    """``frames.rate: null``: only the own-layout frame goes out, the same from both paths."""
    path, message = vendor_setup(tmp_path, "intel-standard")
    content = yaml.safe_load(path.read_text())
    content["frames"] = {"rate": None}
    path.write_text(yaml.safe_dump(content))
    config = load_config(path)
    assert config.rate_message is None
    raws = vendor_stream(message, 100)
    reference, compiled = Daemon(config, compiled=False), Daemon(config)
    sent_ref: list[can.Message] = []

    class RefBus:
        def send(self, msg: can.Message, timeout: float | None = None) -> None:
            sent_ref.append(msg)

    for daemon in (reference, compiled):
        daemon.load_sets()
    feed(reference, raws, RefBus())
    sock = StandInSocket(compiled, [(kernel_frame(m), m.timestamp) for m in raws])
    serve_socket(compiled, sock)
    assert "send_own" in handler_source(compiled)
    assert {m.arbitration_id for m in sent_ref} == {0x298} and len(sent_ref) == 100
    assert sock.sent == [bytes(m.data) for m in sent_ref]
    assert compiled.stats.frames_out == reference.stats.frames_out == 100
    content["own_layout"] = None
    path.write_text(yaml.safe_dump(content))
    with pytest.raises(CanicalError, match=r"frames.rate: null .* needs own_layout"):
        load_config(path)
