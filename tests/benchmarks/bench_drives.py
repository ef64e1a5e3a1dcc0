"""Bias tracking on simulated drives, over seeds: heading, rate error while driving, what a steady
turn and creep in traffic move the learned bias by, gyro only and with a speed cue.

Drives (``canical/sim/drive.py``): 16 minutes of stops with the engine idling, a 40 s steady
15 deg/s turn, creep in traffic, an 8 s stop, three power-ons with different turn-on biases, the
cabin warming from 20 to 45 °C at 0.012 deg/s/°C. ``tests/tracking/test_drives.py`` asserts the
issue's limits on seeds 0–4; this prints the figures and their spread.

Run: python tests/benchmarks/bench_drives.py [--seeds N] [--quick]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
from support.drives import figures


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--seeds", type=int, default=10)
    parser.add_argument("--quick", action="store_true", help="one seed: checks the script runs")
    args = parser.parse_args()
    seeds = range(1 if args.quick else args.seeds)
    runs = {cue: [figures(seed, cue) for seed in seeds] for cue in (False, True)}
    print(f"seeds 0–{len(seeds) - 1}; median (min–max) over seeds\n")
    print("| figure | gyro only | with a speed cue |\n|---|---|---|")
    for name, of, fmt in (
        ("heading error at the end, tracked / untracked (%)", lambda f: 100 * f.heading_ratio, ".2f"),
        ("heading error at the end, untracked (deg)", lambda f: f.heading_untracked_deg, ".0f"),
        ("rate error while driving, tracked (deg/s rms)", lambda f: f.rate_error_tracked_rms_dps, ".4f"),
        ("rate error while driving, untracked (deg/s rms)", lambda f: f.rate_error_untracked_rms_dps, ".3f"),
        ("learned bias moved by the steady turn (deg/s)", lambda f: f.moved_in_turn_dps, ".4f"),
        ("learned bias moved by the creep (deg/s)", lambda f: f.moved_in_creep_dps, ".4f"),
    ):
        cells = []
        for cue in (False, True):
            v = np.array([of(f) for f in runs[cue]])
            cells.append(f"{np.median(v):{fmt}} ({v.min():{fmt}}–{v.max():{fmt}})")
        print(f"| {name} | {cells[0]} | {cells[1]} |")


if __name__ == "__main__":
    main()
