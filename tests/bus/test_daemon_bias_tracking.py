"""The daemon with bias_tracking: on: the same bias as `apply --track-bias`, float for float.

A stream of IMU frames (a standstill, a steady 15 deg/s turn on z, another standstill) goes
through the compiled daemon (generated raw handler) and the reference one in-process. What
each subtracts per frame must equal, bit for bit, what the offline path computes: each axis's
set applied to the block (``Corrector.correct``) and the drive replayed row by row
(``canical.tracking.replay``), on the inputs held per raw frame, which is what
``canical apply SET LOG --config CONFIG --track-bias`` runs.
"""

from __future__ import annotations

import logging
import math
from pathlib import Path

import can
import numpy as np
import pytest
from support.daemon_fixtures import DBC, write_config, write_sets
from test_daemon_compiled import StandInSocket, feed, handler_source, kernel_frame, serve_socket

from canical.bus import bias_tracking
from canical.bus.bias_tracking import DaemonTracking
from canical.bus.daemon import Daemon
from canical.bus.daemon_config import load_config
from canical.bus.link import BusLink
from canical.errors import CanicalError
from canical.frames.codec import load_dbc
from canical.sets import coefficient_file
from canical.sets.corrector import Corrector
from canical.tracking import state_file
from canical.tracking.config import TrackerConfig
from canical.tracking.estimate import AxisBias
from canical.tracking.fast_step import FastStep
from canical.tracking.replay import replay

LIMITS = state_file.StateLimits.of(TrackerConfig())

FS = 100.0
SETTINGS = {"enabled": True, "arw_deg_rt_h": 0.5, "state_file": "bias.json"}


def drive_frames(seconds: float = 45.0, seed: int = 5, turns: tuple[float, float, float] = (0.0, 0.0, 15.0)
                 ) -> list[can.Message]:
    """Standstill 20 s, a steady turn for 12 s (``turns``: deg/s about x, y, z; on z alone unless
    given), standstill again; aux before every 10th raw."""
    db = load_dbc(DBC)
    raw_msg, aux_msg = db.get_message_by_name("IMU_RAW"), db.get_message_by_name("IMU_AUX")
    rng = np.random.default_rng(seed)
    t = np.arange(int(seconds * FS)) / FS
    turning = (t > 20) & (t < 32)
    msgs = []
    for i, ti in enumerate(t):
        stamp = 1000.0 + ti
        if i % 10 == 0:
            msgs.append(can.Message(timestamp=stamp, arbitration_id=aux_msg.frame_id, is_extended_id=False,
                                    data=aux_msg.encode({"SupplyVoltage": 5.0, "Uptime": round(3.0 + ti, 3),
                                                         "AuxCounter": (i // 10) & 0xF})))
        counts = {a: int(37 + 400 * (b + (turn if turning[i] else 0.0) + 0.05 * rng.standard_normal()))
                  for a, b, turn in zip("xyz", (0.2, -0.1, 0.3), turns, strict=True)}
        msgs.append(can.Message(timestamp=stamp, arbitration_id=raw_msg.frame_id, is_extended_id=False,
                                data=raw_msg.encode({"GyroRawX": counts["x"], "GyroRawY": counts["y"],
                                                     "GyroRawZ": counts["z"],
                                                     "Temperature": round(25.0 + 0.1 * ti, 1),
                                                     "Counter": i & 0xF, "SensorFault": 0})))
    return msgs


def offline(folder: Path, msgs: list[can.Message], daemon: Daemon) -> np.ndarray:
    """What apply --track-bias computes per raw frame: each axis's rate less its tracked bias."""
    db = load_dbc(DBC)
    raw_msg, aux_msg = db.get_message_by_name("IMU_RAW"), db.get_message_by_name("IMU_AUX")
    held: dict[str, float] = {}
    rows = []
    for m in msgs:
        if m.arbitration_id == aux_msg.frame_id:
            held.update(aux_msg.decode(m.data))
        else:
            rows.append({**held, **raw_msg.decode(m.data)})
    config = daemon.config
    assert config.bias_tracking is not None
    inputs = {name: np.array([float(r[s.signal]) for r in rows]) for name, s in config.inputs.items()}
    out = []
    for axis in ("x", "y", "z"):
        cset = coefficient_file.load(folder / f"imu-{axis}.yaml")
        raw = np.array([float(r[f"GyroRaw{axis.upper()}"]) for r in rows])
        rate, _ = Corrector(cset).correct(raw, inputs)
        tracked = replay(inputs["time_s"], rate, config.bias_tracking.settings.tracker, axes=(axis,),
                         temp_c=inputs["temp_c"])
        out.append(rate - tracked.bias_dps[:, 0])
    return np.column_stack(out)


@pytest.fixture
def recorded(monkeypatch: pytest.MonkeyPatch) -> list[tuple[float, float, float]]:
    """Every (x, y, z) the daemon's tracking hands back, frame by frame."""
    seen: list[tuple[float, float, float]] = []
    original = DaemonTracking.__call__

    def record(self, *args):  # type: ignore[no-untyped-def]
        out = original(self, *args)
        seen.append(out)
        return out

    monkeypatch.setattr(DaemonTracking, "__call__", record)
    return seen


@pytest.fixture
def stepped(monkeypatch: pytest.MonkeyPatch) -> dict[str, list[float]]:
    """Per axis, each rate less the bias its tracker's step gave, in the order stepped (the
    generated handler calls the steps inline, the reference one through ``DaemonTracking``)."""
    seen: dict[str, list[float]] = {}
    original = bias_tracking.fast_step

    def wrapped(tracker):  # type: ignore[no-untyped-def]
        fast, out = original(tracker), seen.setdefault(tracker.axes[0], [])

        def step(t: float, r: float, temp: float = math.nan, cue: float | None = None) -> float:
            bias = fast.step(t, r, temp, cue)
            out.append(r - bias)
            return bias

        def applied() -> float:  # a frame not stepped: nothing to compare it with
            out.append(math.nan)
            return fast.applied()

        return FastStep(step, applied, fast.sync)

    monkeypatch.setattr(bias_tracking, "fast_step", wrapped)
    return seen


@pytest.mark.parametrize("compiled", [True, False], ids=["generated handler", "reference handler"])
def test_the_daemon_tracks_the_bias_as_apply_does(tmp_path: Path, stepped, compiled: bool,
                                                  caplog: pytest.LogCaptureFixture) -> None:
    write_sets(tmp_path)
    config = load_config(write_config(tmp_path, "trk", bias_tracking=SETTINGS))
    msgs = drive_frames()
    daemon = Daemon(config, compiled=compiled)
    daemon.load_sets()
    if compiled:
        sock = StandInSocket(daemon, [(kernel_frame(m), m.timestamp) for m in msgs])
        serve_socket(daemon, sock)
        assert handler_source(daemon).count("TRK_STEP") >= 1
    else:
        class RefBus:
            def send(self, msg: can.Message, timeout: float | None = None) -> None:
                pass

        feed(daemon, msgs, RefBus())
    expected = offline(tmp_path, msgs, daemon)
    got = np.column_stack([stepped[axis] for axis in ("x", "y", "z")])
    assert got.shape == expected.shape
    assert np.array_equal(got, expected)  # bit for bit
    tracking = daemon.tracking
    assert tracking is not None
    status = {p["axis"]: p for p in tracking.status_pages()}
    assert status["z"]["updates"] > 10 and abs(status["z"]["bias_dps"] - 0.3) < 0.05
    with caplog.at_level(logging.INFO, logger="canical.serve"):
        tracking.log_events()
        tracking.save()
    # the steady 15 deg/s turn is driving: not a standstill, so not logged as one refused
    assert "adopted" in caplog.text and "refused" not in caplog.text
    assert f"z bias {status['z']['bias_dps']:+.4f}" in daemon.status_line()
    loaded = state_file.load(tmp_path / "bias.json", daemon.sets.combined_id, ("x", "y", "z"), LIMITS)
    assert loaded.learned is not None and loaded.learned[2].updates == status["z"]["updates"]
    if not compiled:  # the status frame's page 3: each axis's learned bias, as sent on the bus
        sent: list[can.Message] = []
        bus = type("Bus", (), {"send": lambda self, msg, timeout=None: sent.append(msg)})()
        daemon.sender.link = BusLink(bus)
        daemon._send_status()
        message = load_dbc(DBC).get_message_by_name("CANICAL_STATUS")
        pages = [message.decode(bytes(m.data), decode_choices=False) for m in sent]
        bias = {p["BiasAxis"]: p for p in pages if p["Page"] == 3}
        assert sorted(bias) == [0, 1, 2]
        assert bias[2]["BiasLearned"] == pytest.approx(status["z"]["bias_dps"], abs=1e-4)
        assert bias[2]["BiasSigma"] == pytest.approx(status["z"]["sigma_dps"], abs=1e-4)
        assert bias[2]["BiasUpdates"] == status["z"]["updates"]
        assert bias[2]["BiasAge"] == round(status["z"]["age_s"])


def test_a_restart_starts_from_the_saved_state_and_new_sets_afresh(tmp_path: Path,
                                                                   caplog: pytest.LogCaptureFixture) -> None:
    write_sets(tmp_path)
    config = load_config(write_config(tmp_path, "trk", bias_tracking=SETTINGS))
    first = Daemon(config, compiled=False)
    first.load_sets()
    feed(first, drive_frames(20.0), type("Bus", (), {"send": lambda self, msg, timeout=None: None})())
    assert first.tracking is not None
    first.tracking.save()
    with caplog.at_level(logging.INFO, logger="canical.serve"):
        second = Daemon(config, compiled=False)
        second.load_sets()
        second.raw_path.plans.plan(second.sets)
    assert "window updates for set" in caplog.text and "loaded" in caplog.text
    assert second.tracking is not None and second.tracking.trackers[2] is not None
    assert abs(second.tracking.trackers[2].status()[0].bias_dps - 0.3) < 0.05  # before any frame
    write_sets(tmp_path, variant=1)  # new sets: what was learned is for the old ones
    caplog.clear()
    with caplog.at_level(logging.INFO, logger="canical.serve"):
        third = Daemon(config, compiled=False)
        third.load_sets()
        third.raw_path.plans.plan(third.sets)
    assert "not this set" in caplog.text and "learning afresh" in caplog.text



def test_an_implausible_saved_state_is_refused_with_a_warning(tmp_path: Path,
                                                              caplog: pytest.LogCaptureFixture) -> None:
    """A state file whose CRC is valid but whose bias is 100 deg/s was loaded and applied to every
    frame; now the daemon starts afresh and says so at WARNING (a damaged file is not news)."""
    import json
    write_sets(tmp_path)
    config = load_config(write_config(tmp_path, "trk", bias_tracking=SETTINGS))
    first = Daemon(config, compiled=False)
    first.load_sets()
    path = tmp_path / SETTINGS["state_file"]
    state_file.save(path, first.sets.combined_id, ("x", "y", "z"), [AxisBias(b0=0.3)] * 3)
    body = {k: v for k, v in json.loads(path.read_text()).items() if k != "crc32"}
    for state in body["states"]:
        state["b0"] = 100.0
    path.write_text(json.dumps({**body, "crc32": f"0x{state_file._crc(body):08x}"}))
    with caplog.at_level(logging.INFO, logger="canical.serve"):
        second = Daemon(config, compiled=False)
        second.load_sets()
        second.raw_path.plans.plan(second.sets)
    refused = [r for r in caplog.records if "learning afresh" in r.getMessage()]
    assert [r.levelno for r in refused] == [logging.WARNING], caplog.text
    assert "beyond ±1 deg/s" in refused[0].getMessage()
    assert second.tracking is not None and second.tracking.trackers[2] is not None
    assert second.tracking.trackers[2].status()[0].bias_dps == 0.0

@pytest.mark.parametrize(("section", "message"), [
    ({"enabled": True, "cue": {"input": "speed"}}, "bias_tracking.cue.input: no input 'speed' in inputs"),
    ({"enabled": True, "temperature": "cabin_c"}, "bias_tracking.temperature: no input 'cabin_c'"),
    ({"enabled": "on"}, "bias_tracking.enabled: must be true or false"),
    ({"enabled": True, "window": 1}, "bias_tracking.window: unknown key"),
])
def test_a_bad_section_is_refused_at_start(tmp_path: Path, section: dict, message: str) -> None:
    write_sets(tmp_path)
    with pytest.raises(CanicalError) as info:
        load_config(write_config(tmp_path, "bad", bias_tracking=section))
    assert message in str(info.value) and "\n" not in str(info.value)


def test_apply_with_the_daemon_configuration_tracks_as_the_daemon(tmp_path: Path, recorded,
                                                                  capsys: pytest.CaptureFixture[str]) -> None:
    """apply LOG --config CONFIG --track-bias takes bias_tracking: from the configuration."""
    from canical.commands.cli import main

    write_sets(tmp_path)
    cfg_path = write_config(tmp_path, "trk", bias_tracking={**SETTINGS, "arw_deg_rt_h": 0.4})
    msgs = drive_frames(30.0)
    log = tmp_path / "drive.log"
    with can.Logger(str(log)) as logger:
        for m in msgs:
            logger.on_message_received(m)
    daemon = Daemon(load_config(cfg_path), compiled=False)
    daemon.load_sets()
    feed(daemon, msgs, type("Bus", (), {"send": lambda self, msg, timeout=None: None})())
    out = tmp_path / "z.csv"
    assert main(["apply", str(tmp_path / "imu-z.yaml"), str(log), "--config", str(cfg_path), "--track-bias",
                 "-o", str(out)]) == 0
    assert "as configured in" in capsys.readouterr().out
    lines = out.read_text().splitlines()
    header = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    names = lines[header].split(",")
    table = np.loadtxt(out, delimiter=",", skiprows=header + 1)
    tracked = table[:, names.index("rate_dps")] - table[:, names.index("bias_dps")]
    assert np.max(np.abs(tracked - np.array(recorded)[:, 2])) <= 2e-6  # the file's 6 decimals


@pytest.mark.parametrize(("section", "expected"), [
    ({"enabled": True}, (0.2, None, 0.5)),  # each set's own; a set without one: the default
    ({"enabled": True, "arw_deg_rt_h": 0.4}, (0.4, None, 0.4)),  # configured: it overrides the sets'
])
def test_each_axis_tells_a_standstill_by_its_sets_noise(tmp_path: Path, section: dict,
                                                        expected: tuple) -> None:
    write_sets(tmp_path)
    config = load_config(write_config(tmp_path, "arw", bias_tracking=section))
    assert config.bias_tracking is not None
    tracking = DaemonTracking(config.bias_tracking, {})
    tracking.for_sets(7, ("x", "y", "z"), ({"arw_deg_rt_h": 0.2}, None, {}))
    got = tuple(None if t is None else t.config.arw_deg_rt_h for t in tracking.trackers)
    assert got == expected
