"""The learned bias's state file: kept for its set only, refused whole when damaged, never torn by a kill."""

from __future__ import annotations

import dataclasses
import os
import random
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import pytest

from canical.tracking import state_file
from canical.tracking.estimate import AxisBias

SET_ID = 0x1234ABCD
AXES = ("x", "y", "z")
LEARNED = tuple(AxisBias(b0=0.1 * i, slope=0.012, p00=1e-5, p01=-1e-7, p11=1e-6, updates=7 + i)
                for i in range(3))


def test_a_saved_state_loads_back_exactly(tmp_path: Path) -> None:
    path = tmp_path / "bias.json"
    state_file.save(path, SET_ID, AXES, LEARNED)
    loaded = state_file.load(path, SET_ID, AXES)
    assert loaded.learned is not None
    keep = ("b0", "slope", "p00", "p01", "p11", "updates")
    assert [[getattr(s, f) for f in keep] for s in loaded.learned] == \
        [[getattr(s, f) for f in keep] for s in LEARNED]
    assert "24 window updates for set 0x1234abcd loaded" in loaded.note


def damaged(text: str) -> str:
    return text.replace('"b0": 0.1', '"b0": 0.2')


def with_value(field: str, value: str):
    def edit(text: str) -> str:
        import json
        import zlib

        content = json.loads(text)
        content["states"][0][field] = json.loads(value)
        body = {k: v for k, v in content.items() if k != "crc32"}
        crc = zlib.crc32(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()) & 0xFFFFFFFF
        content["crc32"] = f"0x{crc:08x}"
        return json.dumps(content)
    return edit


@pytest.mark.parametrize(("edit", "why"), [
    (damaged, "damaged (CRC mismatch)"),
    (lambda t: t[: len(t) // 2], "damaged (not JSON)"),
    (lambda t: "", "damaged (not JSON)"),
    (lambda t: '{"a": 1}', "not a canical bias state file"),
    (lambda t: t.replace('"version": 1', '"version": 9'), "version 9 not supported"),
    (with_value("p00", "-1.0"), "covariance is not a covariance"),
    (with_value("slope", '"x"'), "states[0].slope is not a finite number"),
    (with_value("updates", "-3"), "states[0].updates is not a count"),
])
def test_a_damaged_file_starts_afresh_with_one_line(tmp_path: Path, edit, why: str) -> None:
    path = tmp_path / "bias.json"
    path.write_text(edit(state_file.dumps(SET_ID, AXES, LEARNED)))
    loaded = state_file.load(path, SET_ID, AXES)
    assert loaded.learned is None
    assert why in loaded.note and loaded.note.endswith("learning afresh") and "\n" not in loaded.note


def test_another_sets_or_axes_state_is_foreign(tmp_path: Path) -> None:
    path = tmp_path / "bias.json"
    state_file.save(path, SET_ID, AXES, LEARNED)
    other = state_file.load(path, SET_ID + 1, AXES)
    assert other.learned is None and "not this set 0x1234abce" in other.note
    axes = state_file.load(path, SET_ID, ("z", "y", "x"))
    assert axes.learned is None and "learned for axes" in axes.note
    missing = state_file.load(tmp_path / "none.json", SET_ID, AXES)
    assert missing.learned is None and "none yet" in missing.note


WRITER = textwrap.dedent("""
    import sys
    from canical.tracking import state_file
    from canical.tracking.estimate import AxisBias
    path, start = sys.argv[1], int(sys.argv[2])
    print("ready", flush=True)
    n = start
    while True:
        n += 1
        learned = [AxisBias(b0=n * 1e-3, slope=0.01, p00=1e-4, updates=n) for _ in range(3)]
        state_file.save(path, 0x1234ABCD, ("x", "y", "z"), learned)
""")


def test_a_writer_killed_at_random_moments_leaves_the_old_state_or_the_new(tmp_path: Path) -> None:
    """SIGKILL at 120 random moments while a writer saves again and again: the file always loads whole."""
    path = tmp_path / "bias.json"
    state_file.save(path, SET_ID, AXES, [dataclasses.replace(s, updates=0) for s in LEARNED])
    rng = random.Random(20)
    env = {**os.environ, "PYTHONPATH": str(Path(__file__).resolve().parents[2])}
    last = 0
    torn = 0  # kills that landed mid-write: a temporary left beside the file
    for _trial in range(120):
        proc = subprocess.Popen([sys.executable, "-c", WRITER, str(path), str(last)], stdout=subprocess.PIPE,
                                env=env, text=True)
        assert proc.stdout is not None and proc.stdout.readline() == "ready\n"
        time.sleep(rng.uniform(0.0, 0.03))
        proc.send_signal(signal.SIGKILL)
        proc.wait()
        proc.stdout.close()
        leftovers = list(tmp_path.glob(".bias.json.*"))
        torn += bool(leftovers)
        for leftover in leftovers:
            leftover.unlink()
        loaded = state_file.load(path, SET_ID, AXES)
        assert loaded.learned is not None, loaded.note
        updates = loaded.learned[0].updates
        assert updates >= last  # the old state or a newer one, never older
        last = updates
    assert last > 0  # the writer did write between the kills
    assert torn >= 10, f"only {torn} of 120 kills landed during a write"


def test_a_restart_keeps_the_slope_and_relearns_the_turn_on_bias(tmp_path: Path) -> None:
    import numpy as np

    from canical.tracking.config import TrackerConfig
    from canical.tracking.replay import replay

    config = TrackerConfig(arw_deg_rt_h=0.3)
    rng = np.random.default_rng(4)
    t = np.arange(3000) / 100.0
    first = replay(t, 0.3 + 0.05 * rng.standard_normal(t.size), config, axes=("z",))
    path = tmp_path / "bias.json"
    state_file.save(path, SET_ID, ("z",), first.learned)
    loaded = state_file.load(path, SET_ID, ("z",))
    assert loaded.learned is not None
    second = replay(t, -0.1 + 0.05 * rng.standard_normal(t.size), config, axes=("z",), learned=loaded.learned)
    assert second.bias_dps[0, 0] == pytest.approx(0.3, abs=0.01)  # starts from what was learned
    assert second.bias_dps[-1, 0] == pytest.approx(-0.1, abs=0.01)  # and relearns the new turn-on bias
    assert second.learned[0].updates > first.learned[0].updates
