"""The issue's figures on simulated drives, over seeds: python -m tests.tracking.test_drives prints them.

Drives: stops with the engine idling, a 40 s steady turn, creep in traffic, an 8 s stop, three
power-ons with different turn-on biases, the cabin warming from 20 to 45 °C at 0.012 deg/s/°C.
"""

from __future__ import annotations

import math

import pytest

from canical.sim.drive import DriveFigures, DriveModel, drive_figures, simulate_drive
from canical.tracking.config import TrackerConfig
from canical.tracking.replay import replay

SEEDS = range(5)
MODEL = DriveModel()
ARW = MODEL.white_dps / math.sqrt(MODEL.rate_hz) * 60.0  # deg/√h, as the set's noise figure
CUE_MPS = 0.1


def figures(seed: int, cue: bool) -> DriveFigures:
    drive = simulate_drive(seed, MODEL)
    config = TrackerConfig(arw_deg_rt_h=ARW, cue_threshold=CUE_MPS if cue else None)
    out = replay(drive.time_s, drive.rate_dps, config, temp_c=drive.temp_c,
                 cue=drive.speed_mps if cue else None)
    return drive_figures(drive, out.bias_dps, out.taken)


@pytest.mark.parametrize("cue", [False, True], ids=["gyro only", "speed cue"])
@pytest.mark.parametrize("seed", SEEDS)
def test_a_drive_meets_the_issue_figures(seed: int, cue: bool) -> None:
    f = figures(seed, cue)
    assert f.heading_ratio <= 0.05
    assert f.rate_error_tracked_rms_dps <= 0.03
    assert f.rate_error_untracked_rms_dps > 0.25  # the drive does hold an error worth tracking
    assert f.windows_in_turn == 0 and f.moved_in_turn_dps == 0.0
    if cue:
        assert f.moved_in_creep_dps <= 0.01


def main() -> None:
    """Print the figures for each seed and their spread."""
    import numpy as np

    for cue in (False, True):
        rows = [figures(seed, cue) for seed in range(10)]
        print(f"{'speed cue' if cue else 'gyro only'}, 10 seeds:")
        for name, values in (
            ("heading tracked/untracked %", [100 * f.heading_ratio for f in rows]),
            ("heading untracked deg", [f.heading_untracked_deg for f in rows]),
            ("rate error driving tracked dps", [f.rate_error_tracked_rms_dps for f in rows]),
            ("rate error driving untracked dps", [f.rate_error_untracked_rms_dps for f in rows]),
            ("learned bias moved in turn dps", [f.moved_in_turn_dps for f in rows]),
            ("learned bias moved in creep dps", [f.moved_in_creep_dps for f in rows]),
        ):
            v = np.asarray(values)
            print(f"  {name:34s} median {np.median(v):8.4f}  min {v.min():8.4f}  max {v.max():8.4f}")


if __name__ == "__main__":
    main()
