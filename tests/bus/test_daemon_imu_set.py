"""The daemon correcting with an IMU set (``imu_set:``): three axes' models and their coupling, one whole.

In-process, on the stand-in raw socket of ``test_daemon_compiled``: the compiled daemon
(generated handler) and the reference one send the same frames; each frame's rates are the
IMU set applied as ``apply`` applies it (each axis's corrector, then the coupling), not the
per-axis rates; a new IMU set written between two frames is adopted whole at one frame (every
axis and the coupling, one tag); a bad IMU set is refused with one line and the old one kept.
"""

from __future__ import annotations

import math
import subprocess
import sys
from pathlib import Path

import can
import numpy as np
import pytest
import yaml
from support.daemon_fixtures import (
    ALL_TERMS,
    AXES,
    DBC,
    decode_stream,
    imu_set_config,
    imu_stream,
    write_config,
    write_imu_set,
)
from test_daemon_bias_tracking import drive_frames
from test_daemon_compiled import StandInSocket, feed, handler_source, kernel_frame, serve_socket

from canical.bus import bias_tracking
from canical.bus.daemon import Daemon
from canical.bus.daemon_config import load_config
from canical.errors import CanicalError
from canical.files import atomic_file
from canical.frames.codec import load_dbc
from canical.sets import imu_set
from canical.sets.imu_corrector import ImuCorrector
from canical.tracking import state_file
from canical.tracking.config import TrackerConfig
from canical.tracking.fast_step import FastStep3
from canical.tracking.replay import replay

LIMITS = state_file.StateLimits.of(TrackerConfig())

LSB = 0.01  # RateX/Y/Z's resolution in canical.dbc
TRACKING = {"enabled": True, "arw_deg_rt_h": 0.5, "state_file": "bias.json"}


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    write_imu_set(tmp_path, terms=ALL_TERMS)
    (tmp_path / "next").mkdir()
    write_imu_set(tmp_path / "next", terms=ALL_TERMS, variant=1,
                  coupling=((0.998, -0.01, 0.006), (0.009, 1.003, -0.012), (0.017, -0.004, 0.999)))
    return tmp_path


def messages(n: int, seed: int = 3) -> tuple[list[can.Message], list[dict[str, float]]]:
    stream = imu_stream(n, seed=seed)
    msgs = [can.Message(arbitration_id=fid, data=data, is_extended_id=False, timestamp=100.0 + i * 0.001)
            for i, (fid, data) in enumerate(stream.frames)]
    return msgs, decode_stream(stream)


def expected(path: Path, signals: list[dict[str, float]]) -> tuple[np.ndarray, np.ndarray]:
    """What ``apply imu.yaml`` gives for these frames, frame by frame (the direction terms' state
    carried in time order), coupled and per axis."""
    corrector = ImuCorrector(imu_set.load(path))
    raw = np.array([[s[f"GyroRaw{a.upper()}"] for a in AXES] for s in signals])
    inputs = {"temp_c": np.array([s["Temperature"] for s in signals]),
              "time_s": np.array([s.get("Uptime", 0.0) for s in signals]),
              "supply_v": np.array([s.get("SupplyVoltage", 0.0) for s in signals])}
    coupled, _ = corrector.correct(raw, inputs)
    for c in corrector.axes:
        c.reset()
    per_axis, _ = corrector.per_axis(raw, inputs)
    return coupled, per_axis


def sent_rates(payloads: list[bytes]) -> tuple[np.ndarray, list[int]]:
    rate = load_dbc(DBC).get_message_by_name("CANICAL_RATE")
    decoded = [rate.decode(p) for p in payloads]
    return np.array([[d[f"Rate{a.upper()}"] for a in AXES] for d in decoded]), [d["SetTag"] for d in decoded]


def run_both(config_path: Path, msgs: list[can.Message]) -> tuple[Daemon, Daemon, list[bytes], StandInSocket]:
    config = load_config(config_path)
    reference, compiled = Daemon(config, compiled=False), Daemon(config)
    sent_ref: list[bytes] = []

    class RefBus:
        def send(self, msg: can.Message, timeout: float | None = None) -> None:
            sent_ref.append(bytes(msg.data))

    for daemon in (reference, compiled):
        daemon.load_sets()
    feed(reference, msgs, RefBus())
    sock = StandInSocket(compiled, [(kernel_frame(m), m.timestamp) for m in msgs])
    serve_socket(compiled, sock)
    return reference, compiled, sent_ref, sock


@pytest.mark.parametrize("seed", [3, 8, 21])
def test_frames_carry_the_coupled_rates_apply_computes(folder: Path, seed: int) -> None:
    msgs, signals = messages(500, seed)
    reference, compiled, sent_ref, sock = run_both(imu_set_config(folder, "imu"), msgs)
    assert sock.sent == sent_ref and len(sent_ref) == 500
    assert "r0, r1, r2 = " in handler_source(compiled)
    rates, tags = sent_rates(sock.sent)
    coupled, per_axis = expected(folder / "imu-set.yaml", signals)
    inside = np.abs(coupled).max(axis=1) < 327.0  # the frame saturates at its signals' range
    assert inside.sum() > 400
    assert np.abs(rates - coupled)[inside].max() <= LSB / 2 + 1e-9
    assert np.abs(per_axis - coupled)[inside].max() > 20 * LSB  # the coupling is there to see
    imu_id = imu_set.imu_set_crc(imu_set.load(folder / "imu-set.yaml"))
    assert compiled.sets.combined_id == reference.sets.combined_id == imu_id
    assert set(tags) == {compiled.sets.tag}
    assert "coupled" in compiled.sets.describe()


def test_a_new_imu_set_is_adopted_whole_between_two_frames(folder: Path) -> None:
    msgs, signals = messages(600)
    config = load_config(imu_set_config(folder, "swap"))
    daemon = Daemon(config)
    daemon.load_sets()
    first = [k for k, m in enumerate(msgs) if m.arbitration_id == 0x190]
    cut = first[300]  # the message index of raw frame 300
    sock = StandInSocket(daemon, [(kernel_frame(m), m.timestamp) for m in msgs[:cut]])
    serve_socket(daemon, sock)
    old_tag, old_id = daemon.sets.tag, daemon.sets.combined_id
    first_set = folder / "first.yaml"
    first_set.write_text((folder / "imu-set.yaml").read_text())
    atomic_file.write_text_atomic(folder / "imu-set.yaml", (folder / "next" / "imu-set.yaml").read_text())
    daemon._running = True
    daemon._reload(force=False, why="test")
    assert daemon.sets.combined_id != old_id and daemon.sets.coupling is not None
    assert all(ax.reloads == 1 for ax in daemon.sets.axes)
    sock.frames = iter([(kernel_frame(m), m.timestamp) for m in msgs[cut:]])
    serve_socket(daemon, sock)

    rates, tags = sent_rates(sock.sent)
    assert tags == [old_tag] * 300 + [daemon.sets.tag] * 300
    before, _ = expected(first_set, signals[:300])
    # The new set's direction state starts at the frame it is adopted (a new corrector per axis).
    after, _ = expected(folder / "imu-set.yaml", signals[300:])
    want = np.vstack([before, after])
    inside = np.abs(want).max(axis=1) < 327.0
    assert np.abs(rates - want)[inside].max() <= LSB / 2 + 1e-9


def test_a_bad_imu_set_is_refused_in_one_line_and_the_running_one_kept(folder: Path, caplog) -> None:
    config = load_config(imu_set_config(folder, "bad"))
    daemon = Daemon(config)
    daemon.load_sets()
    running = daemon.sets
    content = yaml.safe_load((folder / "imu-set.yaml").read_text())
    content["coupling"]["matrix"][0][1] = 0.15  # an axis mislabelled: refused by the loader
    content.pop("crc32")
    from canical.sets import coefficient_file

    content["crc32"] = f"0x{coefficient_file.content_crc(content):08x}"
    atomic_file.write_text_atomic(folder / "imu-set.yaml", yaml.safe_dump(content, sort_keys=False))
    daemon._reload(force=False, why="test")
    assert daemon.sets.combined_id == running.combined_id and daemon.sets.coupling == running.coupling
    assert any("coupling term xy is +15.0 %" in r.getMessage() and "keeping IMU set" in r.getMessage()
               for r in caplog.records)


def test_configuration_errors_are_one_line(folder: Path) -> None:
    with pytest.raises(CanicalError, match=r"axes.x.coefficients: not with imu_set"):
        load_config(write_config(folder, "both", imu_set=str(folder / "imu-set.yaml")))
    axes = {a: {"raw": f"GyroRaw{a.upper()}"} for a in AXES}
    with pytest.raises(CanicalError, match=r"axes: no axis has a coefficients file"):
        load_config(write_config(folder, "none", axes=axes))


def test_serve_check_loads_the_imu_set_and_refuses_a_bad_one(folder: Path) -> None:
    path = imu_set_config(folder, "chk")
    ok = subprocess.run([sys.executable, "-m", "canical", "serve", "--config", str(path), "--check"],
                        capture_output=True, text=True)
    assert ok.returncode == 0, ok.stderr
    assert "coupling checked" in ok.stdout and "configuration OK" in ok.stdout
    (folder / "imu-set.yaml").write_text((folder / "imu-set.yaml").read_text().replace("0.012", "0.013", 1))
    bad = subprocess.run([sys.executable, "-m", "canical", "serve", "--config", str(path), "--check"],
                         capture_output=True, text=True)
    assert bad.returncode == 2 and "CRC mismatch" in bad.stderr
    assert len(bad.stderr.strip().splitlines()) == 1 and "Traceback" not in bad.stderr


@pytest.fixture
def stepped3(monkeypatch: pytest.MonkeyPatch) -> list[tuple[float, float, float]]:
    """Each frame's three rates less the biases the IMU set's one tracker gave, in step order."""
    seen: list[tuple[float, float, float]] = []
    original = bias_tracking.fast_step3

    def wrapped(tracker):  # type: ignore[no-untyped-def]
        fast = original(tracker)

        def step(t, r0, r1, r2, temp=math.nan, cue=None):  # type: ignore[no-untyped-def]
            b = fast.step(t, r0, r1, r2, temp, cue)
            seen.append((r0 - b[0], r1 - b[1], r2 - b[2]))
            return b

        return FastStep3(step, fast.applied, fast.sync)

    monkeypatch.setattr(bias_tracking, "fast_step3", wrapped)
    return seen


@pytest.mark.parametrize("compiled", [True, False], ids=["generated handler", "reference handler"])
def test_one_tracker_over_the_imu_sets_axes_as_apply_track_bias(tmp_path: Path, stepped3,
                                                                 compiled: bool) -> None:
    write_imu_set(tmp_path)
    config = load_config(imu_set_config(tmp_path, "trk", bias_tracking=TRACKING))
    msgs = drive_frames()
    daemon = Daemon(config, compiled=compiled)
    daemon.load_sets()
    if compiled:
        sock = StandInSocket(daemon, [(kernel_frame(m), m.timestamp) for m in msgs])
        serve_socket(daemon, sock)
        assert "TRK_STEP3" in handler_source(daemon) and "r0, r1, r2 = " in handler_source(daemon)
    else:
        feed(daemon, msgs, type("Bus", (), {"send": lambda self, msg, timeout=None: None})())
    signals = frames_signals(msgs)
    imu = imu_set.load(tmp_path / "imu-set.yaml")
    coupled, _ = expected(tmp_path / "imu-set.yaml", signals)
    assert config.bias_tracking is not None
    tracker = config.bias_tracking.settings.tracker.for_sets(
        [a.fit for a in imu.axes], arw_given=config.bias_tracking.settings.arw_given)
    time_s = np.array([s["Uptime"] for s in signals])
    temp = np.array([s["Temperature"] for s in signals])
    out = replay(time_s, coupled, tracker, axes=AXES, temp_c=temp)
    assert np.array_equal(np.array(stepped3), coupled - out.bias_dps)  # bit for bit
    tracking = daemon.tracking
    assert tracking is not None and len(tracking.trackers) == 1
    assert tracking.set_id == imu_set.imu_set_crc(imu)
    status = {p["axis"]: p for p in tracking.status_pages()}
    assert sorted(status) == ["x", "y", "z"] and status["x"]["updates"] > 10
    tracking.save()
    loaded = state_file.load(tmp_path / "bias.json", imu_set.imu_set_crc(imu), AXES, LIMITS)
    assert loaded.learned is not None and [s.updates for s in loaded.learned] == [
        status[a]["updates"] for a in AXES]


def frames_signals(msgs: list[can.Message]) -> list[dict[str, float]]:
    """Per raw frame, the raw frame's signals and the aux frame's latest (as the daemon holds them)."""
    db = load_dbc(DBC)
    raw_msg, aux_msg = db.get_message_by_name("IMU_RAW"), db.get_message_by_name("IMU_AUX")
    held: dict[str, float] = {}
    rows = []
    for m in msgs:
        if m.arbitration_id == aux_msg.frame_id:
            held.update(aux_msg.decode(m.data))
        else:
            rows.append({**held, **raw_msg.decode(m.data)})
    return rows


#: Couplings far from identity (issue 34): each passed the checks before the diagonal bound and
#: gave non-finite rates (1e308·I), zero rates with no flag (1e-300·I), flipped axes (−I) or an
#: axis all but zeroed (diag(1, 1, 2e-3)).
FAR_FROM_IDENTITY = {
    "1e308 I": ([[1e308, 0.0, 0.0], [0.0, 1e308, 0.0], [0.0, 0.0, 1e308]], "xx is 1e+308"),
    "1e-300 I": ([[1e-300, 0.0, 0.0], [0.0, 1e-300, 0.0], [0.0, 0.0, 1e-300]], "xx is 1e-300"),
    "-I": ([[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]], "xx is -1"),
    "diag(1, 1, 2e-3)": ([[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 2e-3]], "zz is 0.002"),
}


def with_coupling(path: Path, matrix: list[list[float]]) -> None:
    """Replace the IMU set's coupling matrix, CRC recomputed (the mutation reaches the checks)."""
    from canical.sets import coefficient_file

    content = yaml.safe_load(path.read_text())
    content["coupling"]["matrix"] = matrix
    content.pop("crc32")
    content["crc32"] = f"0x{coefficient_file.content_crc(content):08x}"
    atomic_file.write_text_atomic(path, yaml.safe_dump(content, sort_keys=False))


def run_cli(argv: list[str], capsys) -> tuple[int, str, str]:
    """The real entry point in-process: exit status, stdout, stderr."""
    from canical.commands.cli import main

    try:
        code = main(argv)
    except SystemExit as exc:
        code = exc.code if isinstance(exc.code, int) else 1
    out = capsys.readouterr()
    return code, out.out, out.err


@pytest.mark.parametrize("case", FAR_FROM_IDENTITY)
def test_a_coupling_far_from_identity_is_refused_everywhere(folder: Path, case: str, caplog, capsys) -> None:
    """apply and serve --check refuse it in one line (exit 2, no traceback, no output file); the
    daemon never loads it, at start or on reload (the running IMU set is kept)."""
    matrix, said = FAR_FROM_IDENTITY[case]
    config = load_config(imu_set_config(folder, "far"))
    daemon = Daemon(config)
    daemon.load_sets()
    running = daemon.sets
    assert running.coupling is not None
    with_coupling(folder / "imu-set.yaml", matrix)
    daemon._reload(force=False, why="test")
    assert daemon.sets.combined_id == running.combined_id and daemon.sets.coupling == running.coupling
    fresh = Daemon(load_config(config.path))
    fresh.load_sets()
    assert fresh.sets.coupling is None and not any(a.corrector for a in fresh.sets.axes)
    refusals = [r.getMessage() for r in caplog.records if said in r.getMessage()]
    assert refusals and all("\n" not in m for m in refusals)
    drive = folder / "drive.csv"
    drive.write_text("time_s,raw_x,raw_y,raw_z\n0.0,100,200,300\n0.01,110,210,310\n")
    out = folder / "out.csv"
    for argv in (["apply", str(folder / "imu-set.yaml"), str(drive), "-o", str(out)],
                 ["serve", "--config", str(config.path), "--check"]):
        code, _, err = run_cli(argv, capsys)
        assert code == 2 and said in err and len(err.strip().splitlines()) == 1, (argv, err)
        assert "Traceback" not in err and "near identity" in err
    assert not out.exists()
