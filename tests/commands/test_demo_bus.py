"""The bus half of the demo is deterministic: one seed, the same frames recorded and compared.

Two runs on python-can's in-process virtual bus, with a short table programme, must record the
same calibration session and compare the same field frames (chosen by the device's sample
index, not by when the push happened to finish), so every figure but timings and the set id
(which covers the set's creation time) is the same.
"""

import uuid
from dataclasses import replace

import numpy as np

from canical.commands.demo_bus import BusDemoOptions, FieldWindow, run_bus_demo

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


def test_field_window_moves_to_the_next_pass_when_the_set_ran_late():
    """A slow machine: the new set runs only after the wanted pass began."""
    from canical.bus.recording import Recording

    fs, pass_samples = 10.0, 100
    window = FieldWindow(tag=5, fs_hz=fs, pass_samples=pass_samples, n=20, pass_index=1)
    rec = Recording()
    done_at = None
    for k in range(0, 400):
        rec.columns["time_s"].append(k / fs)
        rec.columns["device_tag"].append(5.0 if k >= 130 else 3.0)
        if window(rec) and done_at is None:
            done_at = k
    assert window.first_tagged == 130
    assert window.start == 200  # pass 2: pass 1 had begun before the set ran
    assert done_at == 221  # sample 220 seen (the newest is left for its corrected frame)
    assert "pass 2: pass 1 had begun" in window.describe()
    selected = np.flatnonzero(window.selects(rec))
    assert selected[0] == 200 and selected[-1] == 219
