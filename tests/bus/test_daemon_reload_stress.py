"""Many hot reloads while frames stream: every frame is corrected by exactly one generation of sets.

The daemon's whole loop runs in-process (``Daemon.run``: raw-socket receive loop, compiled
codecs and correctors, periodic step, reload worker thread, SIGHUP through the real signal
handler) on a stand-in raw socket that hands out an IMU stream at bus pace. Another thread
replaces the set files and sends SIGHUP, again and again, at moments that fall anywhere in the
frame processing. The test records when the daemon adopted each generation (the number of raw
frames handled by then) and replays the same frames through an independent reference: the
reference per-frame path (``compiled=False``: cantools, ``Corrector.correct_one``) on
correctors of its own, switching to each generation's sets exactly there — fresh correctors
(fresh direction, slope and lag state) for the axes whose set changed, the running ones kept
for the axes whose set stayed. Every payload the daemon sent must be that reference's, byte
for byte: a frame corrected with a mix of two generations, with state shared between an old
and a new corrector, or with a stale compiled function, would differ.
"""

from __future__ import annotations

import dataclasses
import gc
import socket
import time
import weakref
from collections.abc import Callable
from pathlib import Path

import can
import pytest
from support.daemon_fixtures import ALL_TERMS, AXES, base_set, decode_stream, imu_stream, write_config
from support.sighup_operator import Offer, run_with_operator

from canical.bus.active_sets import SOURCE_FILE, ActiveSets, AxisSet, build
from canical.bus.daemon import Daemon
from canical.bus.daemon_config import load_config
from canical.bus.link import SocketLink
from canical.bus.reloads import Reload
from canical.bus.socketcan_constants import FRAME_HEAD, TIMEVAL
from canical.files.atomic_file import write_text_atomic
from canical.frames.codec import load_dbc
from canical.sets import coefficient_file
from canical.sets.corrector import Corrector
from canical.sets.terms import term_from_dict

#: ALL_TERMS plus the stateful channel kinds (lag on x, direction on y, derivative on z: state
#: in the corrector's trackers, shared by the generated code) and the rate gate on z, each kept
#: or started fresh across the reloads.
TERMS = {
    "x": (*ALL_TERMS["x"], {"kind": "channel", "channel": "temp_c", "feature": "lag", "form": "bias",
                            "coefficient": 0.5, "reference": 25.0, "tau_s": 0.02}),
    "y": (*ALL_TERMS["y"], {"kind": "channel", "channel": "temp_c", "feature": "direction", "form": "bias",
                            "coefficient": 0.3, "threshold_raw": 0.5}),
    "z": (*ALL_TERMS["z"], {"kind": "channel", "channel": "temp_c", "feature": "derivative", "form": "scale",
                            "coefficient": 0.01, "tau_s": 0.05},
          {"kind": "channel", "channel": "supply_v", "feature": "gated", "form": "scale",
           "coefficient": 0.002, "reference": 4.0, "threshold_raw": 300.0}),
}
GENERATIONS = 14
SPACING = 300  # raw frames between two reload requests, at least
FRAME_GAP_S = 1e-4  # the stand-in bus's pace: frames keep coming while a reload is built


def variant(gen: int, axis: str) -> int:
    """Which set an axis runs in a generation: x and y change every time, z every other time
    (its corrector, and its state, must then carry on)."""
    return gen // 2 if axis == "z" else gen


class PacedSocket:
    """python-can's raw socket as the daemon uses it, handing out ``frames`` at a steady pace."""

    family = socket.AF_CAN

    def __init__(self, daemon: Daemon, frames: list[tuple[bytes, float]]) -> None:
        self.daemon = daemon
        self.frames = iter(frames)
        self.sent: list[tuple[int, bytes]] = []

    def gettimeout(self) -> None:
        return None

    def setsockopt(self, level: int, option: int, value: bytes) -> None:
        pass

    def recvmsg(self, size: int, ancsize: int):
        time.sleep(FRAME_GAP_S)
        got = next(self.frames, None)
        if got is None:
            self.daemon.request_stop()
            raise BlockingIOError
        cf, stamp = got
        return cf, [(socket.SOL_SOCKET, 35, TIMEVAL.pack(int(stamp), round(stamp % 1 * 1e9)))], 0, None

    def close(self) -> None:
        pass

    def send(self, frame: bytes, flags: int = 0) -> int:
        can_id, length, _, _ = FRAME_HEAD.unpack_from(frame)
        self.sent.append((can_id, frame[8:8 + length]))
        return len(frame)




def reference_sets(folders: list[Path], config_axes, previous: ActiveSets | None, gen: int) -> ActiveSets:
    """Generation ``gen`` as the daemon should run it, on correctors of the reference's own."""
    axes = []
    for i, ax in enumerate(config_axes):
        v = variant(gen, ax.axis)
        if previous is not None and v == variant(gen - 1, ax.axis):
            axes.append(previous.axes[i])  # unchanged set: the same corrector carries on
            continue
        corrector = Corrector(coefficient_file.load(folders[v] / f"imu-{ax.axis}.yaml"))
        axes.append(AxisSet(ax.axis, ax.raw_signal, corrector=corrector, set_id=corrector.set_id,
                            source=SOURCE_FILE))
    return build(tuple(axes))


def test_every_frame_is_corrected_by_exactly_one_generation(tmp_path: Path) -> None:
    base = base_set("z")
    folders = []
    for v in range(GENERATIONS):
        folder = tmp_path / f"v{v}"
        folder.mkdir()
        for axis in AXES:  # variants differ by 40 raw units of V0 (0.1 deg/s) on every axis
            cset = dataclasses.replace(base, axis=axis, terms=tuple(term_from_dict(t) for t in TERMS[axis]),
                                       v0=base.v0 + 40.0 * v)
            coefficient_file.save(folder / f"imu-{axis}.yaml", cset)
        folders.append(folder)
    live = tmp_path / "live"
    live.mkdir()
    for axis in AXES:
        write_text_atomic(live / f"imu-{axis}.yaml", (folders[0] / f"imu-{axis}.yaml").read_text())
    config = load_config(write_config(live, "stress", watch_period_s=3600.0, status_period_s=0.05))

    stream = imu_stream(SPACING * (GENERATIONS + 2), seed=11)
    msgs = [can.Message(arbitration_id=fid, data=data, is_extended_id=False, timestamp=1000.0 + i * 1e-3)
            for i, (fid, data) in enumerate(stream.frames)]
    frames = [(FRAME_HEAD.pack(m.arbitration_id, 8, 0, 0) + bytes(m.data), m.timestamp) for m in msgs]

    daemon: Daemon
    sock: PacedSocket
    adopted: list[tuple[int, ActiveSets]] = []

    daemon = Daemon(config, open_link=lambda channel, matches: SocketLink(sock))  # type: ignore[arg-type]
    sock = PacedSocket(daemon, frames)
    adopt = daemon._adopt

    def recording_adopt(done: Reload) -> None:
        adopt(done)
        if done.changed and daemon.sets is done.new:
            adopted.append((daemon.stats.frames_in, done.new))  # raw frames handled with the old sets

    daemon._adopt = recording_adopt  # type: ignore[method-assign]

    def replace_changed(gen: int) -> Callable[[], None]:
        def write() -> None:
            for axis in AXES:
                if variant(gen, axis) != variant(gen - 1, axis):
                    text = (folders[variant(gen, axis)] / f"imu-{axis}.yaml").read_text()
                    write_text_atomic(live / f"imu-{axis}.yaml", text)
        return write

    # Replace the changed set files, SIGHUP, wait for the adoption; a second SIGHUP at times,
    # while the first reload is still being built.
    run_with_operator(daemon, [Offer(gen * SPACING, replace_changed(gen), lambda gen=gen: len(adopted) >= gen,
                                     f"generation {gen} adopted", hups=2 if gen % 3 == 0 else 1)
                               for gen in range(1, GENERATIONS)])
    assert len(adopted) == GENERATIONS - 1

    # The reference, sharing no per-frame code with the daemon: the same frames, the same
    # switch points, correctors of its own (Corrector.correct_one), cantools to encode.
    db = load_dbc(config.dbc_path)
    rate = db.get_message_by_name(config.rate_message)
    lo, hi = rate.get_signal_by_name("RateX").minimum, rate.get_signal_by_name("RateX").maximum
    sets = reference_sets(folders, config.axes, None, 0)
    switches = iter([*adopted, (-1, None)])
    at, theirs = next(switches)
    gen = 0
    expected = []
    for i, s in enumerate(decode_stream(stream)):
        while i == at:
            gen += 1
            sets = reference_sets(folders, config.axes, sets, gen)
            assert theirs.combined_id == sets.combined_id, f"generation {gen} is not the sets written"
            at, theirs = next(switches)
        inputs = {"temp_c": s["Temperature"], "time_s": s["Uptime"], "supply_v": s["SupplyVoltage"]}
        fields = {"Stale": 0, "CounterGap": 0, "SetTag": sets.tag, "Counter": i & 0xF}
        for ax in sets.axes:
            value, out = ax.corrector.correct_one(s[ax.raw_signal], inputs)
            name = ax.axis.upper()
            fields |= {f"Rate{name}": min(max(value, lo), hi), f"OutOfSpan{name}": int(out),
                       f"Uncalibrated{name}": 0}
        expected.append(bytes(rate.encode(fields)))
    assert gen == GENERATIONS - 1

    sent = [payload for can_id, payload in sock.sent if can_id == rate.frame_id]
    assert len(sent) == len(expected) == len(stream.raw_index)
    wrong = [i for i, (a, b) in enumerate(zip(sent, expected, strict=True)) if a != b]
    assert not wrong, f"{len(wrong)} frames differ from the reference, first at raw frames {wrong[:5]}; " \
                      f"switches at {[n for n, _ in adopted]}"
    # Each switch came after its files were written (at frame gen * SPACING or later), one
    # generation at a time; how soon after is the machine's speed, not asserted here.
    for gen, (n, _) in enumerate(adopted, start=1):
        assert gen * SPACING <= n, (gen, n)
    assert [n for n, _ in adopted] == sorted({n for n, _ in adopted})



@pytest.mark.parametrize("compiled", [True, False])
def test_replaced_correctors_are_released(tmp_path: Path, compiled: bool) -> None:
    """A replaced set's corrector, compiled or on the reference path (``compiled`` off), is
    freed once no generation uses it: a daemon reloaded for months does not grow."""
    base = base_set("z")
    for v, folder in enumerate((tmp_path, tmp_path / "next")):
        folder.mkdir(exist_ok=True)
        for axis in AXES:
            cset = dataclasses.replace(base, axis=axis, terms=tuple(term_from_dict(t) for t in TERMS[axis]),
                                       v0=base.v0 + 40.0 * v)
            coefficient_file.save(folder / f"imu-{axis}.yaml", cset)
    daemon = Daemon(load_config(write_config(tmp_path, "leak")), compiled=compiled)
    daemon.load_sets()
    daemon.raw_path.plans.plan(daemon.sets)
    old = [weakref.ref(ax.corrector) for ax in daemon.sets.axes]
    for axis in AXES:
        write_text_atomic(tmp_path / f"imu-{axis}.yaml", (tmp_path / "next" / f"imu-{axis}.yaml").read_text())
    daemon._reload(force=False, why="test")
    daemon.raw_path.plans.plan(daemon.sets)
    gc.collect()
    assert [ref() for ref in old] == [None, None, None]
    assert len(daemon.raw_path.plans.compiled_axes) == 3
