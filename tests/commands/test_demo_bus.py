"""The bus half of the demo is deterministic: one seed, the same frames recorded and compared.

Two runs on python-can's in-process virtual bus, with a short table programme, must record the
same calibration session and compare the same field frames (chosen by the device's sample
index, not by when the push happened to finish), so every figure but timings and the set id
(which covers the set's creation time) is the same.
"""

import uuid
from dataclasses import replace

import numpy as np

from canical.bus.recording import Recording
from canical.commands.demo_bus import BusDemoOptions, FieldWindow, NewSetRule, run_bus_demo

SMALL = BusDemoOptions(sample_rate_hz=50.0, speed=8.0, dwell_s=2.0, field_samples=300, field_pass=4,
                       table_rates=tuple(float(r) for r in range(-60, 61, 10)))


def run(folder):
    said: list[str] = []
    options = replace(SMALL, channel=f"demo-{uuid.uuid4().hex}")
    return run_bus_demo(folder, options, say=said.append), said


def test_two_runs_record_and_compare_the_same_frames(tmp_path):
    first, said_first = run(tmp_path / "a")
    second, said_second = run(tmp_path / "b")
    wanted = f"table pass {SMALL.field_pass}, chosen by sample index"
    assert any(wanted in line for line in said_first), said_first
    assert any(wanted in line for line in said_second), said_second
    for name in ("bus-session.csv", "bus-field.csv"):
        assert (tmp_path / "a" / name).read_text() == (tmp_path / "b" / name).read_text(), name
    assert first.field_samples == second.field_samples > 0.9 * SMALL.field_samples
    assert first.held_out_rms_before_dps == second.held_out_rms_before_dps
    assert first.held_out_rms_after_dps == second.held_out_rms_after_dps
    assert first.live_rms_error_dps == second.live_rms_error_dps
    assert first.max_device_vs_apply_dps <= 0.0051


def recording(tags: list[float], rates: list[float], fs: float = 10.0) -> Recording:
    """Samples k = 0.. at ``fs``, received at k / fs, with the device's tag and axis-z rate."""
    rec = Recording()
    for k, (tag, rate) in enumerate(zip(tags, rates, strict=True)):
        rec.columns["time_s"].append(k / fs)
        rec.columns["received_s"].append(k / fs)
        rec.columns["device_tag"].append(tag)
        rec.columns["device_rate_z"].append(rate)
    return rec


def first_window_sample(rule: NewSetRule, rec: Recording) -> int | None:
    window = FieldWindow(rule, fs_hz=10.0, pass_samples=1000, n=5, pass_index=None)
    window(rec)
    return window.first_tagged


def test_field_window_moves_to_the_next_pass_when_the_set_ran_late():
    """A slow machine: the new set runs only after the wanted pass began."""
    fs, pass_samples = 10.0, 100
    rule = NewSetRule(tag=5, axis="z", not_before_s=-np.inf)
    window = FieldWindow(rule, fs_hz=fs, pass_samples=pass_samples, n=20, pass_index=1)
    rec = Recording()
    done_at = None
    for k in range(0, 400):
        rec.columns["time_s"].append(k / fs)
        rec.columns["received_s"].append(k / fs)
        rec.columns["device_tag"].append(5.0 if k >= 130 else 3.0)
        rec.columns["device_rate_z"].append(1.0)
        if window(rec) and done_at is None:
            done_at = k
    assert window.first_tagged == 130
    assert window.start == 200  # pass 2: pass 1 had begun before the set ran
    assert done_at == 221  # sample 220 seen (the newest is left for its corrected frame)
    assert "pass 2: pass 1 had begun" in window.describe()
    selected = np.flatnonzero(window.selects(rec))
    assert selected[0] == 200 and selected[-1] == 219


def test_a_fresh_devices_tag_equal_to_the_new_sets_is_not_taken_for_it():
    """One new set in 16 has the tag of "no set" (15): the frames before activation carry it too,
    uncalibrated; the window begins at the first frame with a rate."""
    nan = float("nan")
    before = recording([15.0] * 10, [nan] * 10)
    rule = NewSetRule.after(before, 15, "z", pushed_at_s=5.0)
    assert not rule.ambiguous  # the axis had no rate before: nothing to confuse
    live = recording([15.0] * 40, [nan] * 12 + [2.0] * 28)
    assert first_window_sample(rule, live) == 12


def test_an_old_set_with_the_new_sets_tag_counts_only_after_the_push_returned():
    before = recording([7.0] * 10, [1.0] * 10)
    rule = NewSetRule.after(before, 7, "z", pushed_at_s=2.05)
    assert rule.ambiguous
    live = recording([7.0] * 40, [1.0] * 40)
    assert first_window_sample(rule, live) == 21  # the first received at or after 2.05 s


def test_a_new_tag_unlike_the_old_counts_from_its_first_frame():
    before = recording([7.0] * 10, [1.0] * 10)
    rule = NewSetRule.after(before, 9, "z", pushed_at_s=2.05)
    assert not rule.ambiguous
    live = recording([7.0] * 8 + [9.0] * 32, [1.0] * 40)
    assert first_window_sample(rule, live) == 8


def test_the_loop_compares_only_frames_of_the_new_set_when_every_tag_collides(tmp_path, monkeypatch):
    """Every set tag forced to 15, the tag of "no set": the frames streamed before the activation
    carry the new set's tag too, and the window must still begin with the new set's first frame."""
    monkeypatch.setattr("canical.device.emulated_imu.set_tag", lambda ids: 15)
    monkeypatch.setattr("canical.commands.demo_bus.set_tag", lambda ids: 15)
    options = replace(SMALL, channel=f"demo-{uuid.uuid4().hex}", field_pass=None, field_samples=200)
    result = run_bus_demo(tmp_path, options, say=lambda line: None)
    assert result.field_samples >= 0.9 * options.field_samples
    assert result.max_device_vs_apply_dps <= 0.0051
