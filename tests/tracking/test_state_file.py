"""The learned bias's state file: kept for its set only, refused whole when damaged, never torn by a kill."""

from __future__ import annotations

import dataclasses
import json
import os
import random
import signal
import time
import zlib
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canical.tracking import state_file
from canical.tracking.config import TrackerConfig
from canical.tracking.estimate import AxisBias

LIMITS = state_file.StateLimits.of(TrackerConfig())

SET_ID = 0x1234ABCD
AXES = ("x", "y", "z")
LEARNED = tuple(AxisBias(b0=0.1 * i, slope=0.012, p00=1e-5, p01=-1e-7, p11=1e-6, updates=7 + i)
                for i in range(3))


def test_a_saved_state_loads_back_exactly(tmp_path: Path) -> None:
    path = tmp_path / "bias.json"
    state_file.save(path, SET_ID, AXES, LEARNED)
    loaded = state_file.load(path, SET_ID, AXES, LIMITS)
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
    loaded = state_file.load(path, SET_ID, AXES, LIMITS)
    assert loaded.learned is None
    assert why in loaded.note and loaded.note.endswith("learning afresh") and "\n" not in loaded.note


def test_another_sets_or_axes_state_is_foreign(tmp_path: Path) -> None:
    path = tmp_path / "bias.json"
    state_file.save(path, SET_ID, AXES, LEARNED)
    other = state_file.load(path, SET_ID + 1, AXES, LIMITS)
    assert other.learned is None and "not this set 0x1234abce" in other.note
    axes = state_file.load(path, SET_ID, ("z", "y", "x"), LIMITS)
    assert axes.learned is None and "learned for axes" in axes.note
    missing = state_file.load(tmp_path / "none.json", SET_ID, AXES, LIMITS)
    assert missing.learned is None and "none yet" in missing.note


def _write_forever(path: Path, start: int, ready: int) -> None:
    """The forked writer: saves ever newer states until it is killed (never returns)."""
    try:
        os.write(ready, b"r")
        n = start
        while True:
            n += 1
            # The bias stays within the ±1 deg/s plausibility bound however long the writer runs.
            learned = [AxisBias(b0=(n % 900) * 1e-3, slope=0.01, p00=1e-4, updates=n) for _ in range(3)]
            state_file.save(path, 0x1234ABCD, ("x", "y", "z"), learned)
    finally:
        os._exit(0)


def test_a_writer_killed_at_random_moments_leaves_the_old_state_or_the_new(tmp_path: Path) -> None:
    """SIGKILL at 120 random moments while a writer saves again and again: the file always loads whole.

    The writer is a forked copy of this process (no interpreter start per trial), killed as a
    power cut or the OOM killer would: no handler, no flush, whatever it was doing."""
    path = tmp_path / "bias.json"
    state_file.save(path, SET_ID, AXES, [dataclasses.replace(s, updates=0) for s in LEARNED])
    rng = random.Random(20)
    last = 0
    torn = 0  # kills that landed mid-write: a temporary left beside the file
    for _trial in range(120):
        ready_r, ready_w = os.pipe()
        pid = os.fork()
        if pid == 0:
            os.close(ready_r)
            _write_forever(path, last, ready_w)
        os.close(ready_w)
        assert os.read(ready_r, 1) == b"r"
        os.close(ready_r)
        time.sleep(rng.uniform(0.0, 0.03))
        os.kill(pid, signal.SIGKILL)
        os.waitpid(pid, 0)
        leftovers = list(tmp_path.glob(".bias.json.*"))
        torn += bool(leftovers)
        for leftover in leftovers:
            leftover.unlink()
        loaded = state_file.load(path, SET_ID, AXES, LIMITS)
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
    loaded = state_file.load(path, SET_ID, ("z",), LIMITS)
    assert loaded.learned is not None
    second = replay(t, -0.1 + 0.05 * rng.standard_normal(t.size), config, axes=("z",), learned=loaded.learned)
    assert second.bias_dps[0, 0] == pytest.approx(0.3, abs=0.01)  # starts from what was learned
    assert second.bias_dps[-1, 0] == pytest.approx(-0.1, abs=0.01)  # and relearns the new turn-on bias
    assert second.learned[0].updates > first.learned[0].updates


def with_crc(body: dict) -> str:
    """A state file's text around ``body``, its CRC recomputed: the mutation reaches the checks."""
    import json
    return json.dumps({**body, "crc32": f"0x{state_file._crc(body):08x}"})


def good_body() -> dict:
    import json
    text = state_file.dumps(SET_ID, AXES, LEARNED)
    return {k: v for k, v in json.loads(text).items() if k != "crc32"}


@pytest.mark.parametrize(("field", "value"), [
    ("b0", 100.0), ("b0", 1.2e21), ("b0", 1e300), ("b0", -1.5), ("slope", -1e308), ("slope", 0.5),
    ("p00", 1e6), ("p11", 1.0), ("b0", 10**400), ("slope", -(10**400)), ("updates", 10**400),
])
def test_an_implausible_state_with_a_valid_crc_is_refused(tmp_path: Path, field: str, value) -> None:
    """A CRC tells damage, not sense: a valid CRC over a 100 deg/s bias was applied to every frame,
    and a slope of -1e308 crashed the daemon at its first status frame."""
    body = good_body()
    body["states"][1][field] = value
    if field == "p00":
        body["states"][1]["p01"] = 0.0
    path = tmp_path / "bias.json"
    path.write_text(with_crc(body))
    loaded = state_file.load(path, SET_ID, AXES, LIMITS)
    assert loaded.learned is None and loaded.refused
    assert len(loaded.note.splitlines()) == 1 and len(loaded.note) < 300, loaded.note
    assert "learning afresh" in loaded.note


@pytest.mark.parametrize("text", [
    "[" * 1000 + "]" * 1000,
    '{"a": ' * 5000 + "1" + "}" * 5000,
    "1" * 5000,
    " " * (state_file.MAX_BYTES + 1) + "{}",
])
def test_deep_huge_or_oversized_text_is_one_line_not_a_traceback(tmp_path: Path, text: str) -> None:
    path = tmp_path / "bias.json"
    path.write_text(text)
    loaded = state_file.load(path, SET_ID, AXES, LIMITS)
    assert loaded.learned is None and loaded.refused
    assert len(loaded.note.splitlines()) == 1 and len(loaded.note) < 300, loaded.note


def test_the_limits_are_the_trackers_own() -> None:
    from canical.tracking.config import TrackerConfig
    wide = state_file.StateLimits.of(TrackerConfig(bound_dps=3.0, temp_slope_sigma=0.05))
    assert wide.bias_dps == 3.0 and wide.slope_dps_per_c == pytest.approx(0.25)
    body = good_body()
    body["states"][0]["b0"] = 2.0
    text = with_crc(body)
    with pytest.raises(ValueError, match=r"states\[0\]\.b0 2 is beyond ±1 deg/s"):
        state_file.parse(text, SET_ID, AXES, LIMITS)
    assert state_file.parse(text, SET_ID, AXES, wide)[0].b0 == 2.0


@settings(max_examples=300, deadline=None)
@given(st.data())
def test_mutated_states_with_their_crc_recomputed_never_raise_nor_load_beyond_the_limits(data) -> None:
    body = good_body()
    k = data.draw(st.integers(0, 2))
    key = data.draw(st.sampled_from([*state_file.FIELDS, "updates"]))
    body["states"][k][key] = data.draw(st.one_of(
        st.floats(allow_nan=True, allow_infinity=True), st.integers(-(10**30), 10**30),
        st.booleans(), st.none(), st.text(max_size=5), st.lists(st.integers(), max_size=3)))
    try:
        learned = state_file.parse(with_crc(body), SET_ID, AXES, LIMITS)
    except ValueError as exc:
        assert len(str(exc).splitlines()) == 1
        return
    for s in learned:
        assert abs(s.b0) <= LIMITS.bias_dps and abs(s.slope) <= LIMITS.slope_dps_per_c
        assert 0 <= s.p00 <= LIMITS.p00 and 0 <= s.p11 <= LIMITS.p11


@pytest.mark.parametrize(("key", "value"), [
    ("set_id", "x" * 5000), ("axes", "a\nb"), ("version", [[[[1]]]] * 300)])
def test_a_foreign_value_is_echoed_in_one_short_line(tmp_path: Path, key: str, value) -> None:
    """The fuzzer's finding: a set id of 5,000 characters (CRC recomputed) made a note as long,
    one with a line break a note of two lines."""
    content = json.loads(state_file.dumps(SET_ID, AXES, LEARNED))
    content[key] = value
    body = {k: v for k, v in content.items() if k != "crc32"}
    content["crc32"] = f"0x{zlib.crc32(json.dumps(body, sort_keys=True, separators=(',', ':')).encode()):08x}"
    path = tmp_path / "bias.json"
    path.write_text(json.dumps(content))
    loaded = state_file.load(path, SET_ID, AXES, LIMITS)
    assert loaded.learned is None and loaded.refused
    assert "\n" not in loaded.note and len(loaded.note) < len(str(path)) + 120, loaded.note


def test_a_key_given_twice_is_refused(tmp_path: Path) -> None:
    """json keeps the last of two equal keys without a word; a state file with one is refused,
    as a YAML file is (the CRC recomputed over what json would have kept)."""
    text = state_file.dumps(SET_ID, AXES, LEARNED)
    twice = text.replace('"b0": ', '"b0": 0.5, "b0": ', 1)
    content = json.loads(twice)
    body = {k: v for k, v in content.items() if k != "crc32"}
    crc = zlib.crc32(json.dumps(body, sort_keys=True, separators=(",", ":")).encode())
    path = tmp_path / "bias.json"
    path.write_text(twice.replace(content["crc32"], f"0x{crc:08x}"))
    loaded = state_file.load(path, SET_ID, AXES, LIMITS)
    assert loaded.learned is None and loaded.refused and "key 'b0' given twice" in loaded.note
