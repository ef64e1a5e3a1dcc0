"""A simulated drive replayed through the bias tracker, and its figures: what the drive tests
assert and ``bench_drives.py`` prints."""

from __future__ import annotations

import math

from canical.sim.drive import DriveFigures, DriveModel, drive_figures, simulate_drive
from canical.tracking.config import TrackerConfig
from canical.tracking.replay import replay

MODEL = DriveModel()
ARW = MODEL.white_dps / math.sqrt(MODEL.rate_hz) * 60.0  # deg/√h, as the set's noise figure
CUE_MPS = 0.1


def figures(seed: int, cue: bool) -> DriveFigures:
    drive = simulate_drive(seed, MODEL)
    config = TrackerConfig(arw_deg_rt_h=ARW, cue_threshold=CUE_MPS if cue else None)
    out = replay(drive.time_s, drive.rate_dps, config, temp_c=drive.temp_c,
                 cue=drive.speed_mps if cue else None)
    return drive_figures(drive, out.bias_dps, out.taken)
