"""The table grid through the bus flow: the emulated IMU streams while a rate table ramps,
rings and reports its measured rate in asynchronous TABLE_REF frames, IMU frames are lost in
bursts; `canical record` writes the log and `canical calibrate` reads it.

In-process on python-can's virtual bus (fast; one pass, deterministic, checked against the
table's truth), and on a real SocketCAN vcan with every piece in its own process (marked vcan;
inside the user-mode Linux guest here). Every grid cell on the virtual bus:
tests/trials/test_table_grid_bus.py.
"""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from support.daemon_fixtures import DBC
from support.trials.table_grid_bus import bus_cell

from canical.commands.cli import main
from canical.sim.table_recording import TableBehaviour

RATES = tuple(float(r) for r in range(-30, 31, 5))  # 13 plateaus, 0 included
DWELL_S = 4.0
#: Bus cells: (name, emulate options, the same as a TableBehaviour).
CELLS = {
    "ramp 3 deg/s², measured 0.02 at 10 Hz async, 3% lost": (
        ["--table-accel", "3", "--table-measured", "0.02", "--table-ref-rate", "10", "--lost-rows", "0.03"],
        TableBehaviour(accel_dps2=3.0, reference="measured", jitter_dps=0.02, encoder_lsb_dps=0.0001,
                       ref_rate_hz=10.0, asynchronous=True, loss_fraction=0.03),
    ),
    "S-curve 10/20, overshoot 10%, 30 ms late": (
        ["--table-accel", "10", "--table-jerk", "20", "--table-overshoot", "0.1", "--table-latency", "0.03"],
        TableBehaviour(accel_dps2=10.0, jerk_dps3=20.0, overshoot=0.1, ref_latency_s=0.03),
    ),
}


def _calibrate(log: Path, folder: Path) -> dict:
    report = folder / "report.json"
    assert main(["calibrate", str(log), "--dbc", str(DBC), "--input", "time_s=IMU_AUX.Uptime", "--no-extend",
                 "--sensor", "IMU-BUS", "-o", str(folder / "set.yaml"), "--report", str(report)]) == 0
    return json.loads(report.read_text())


def _check(report: dict, in_process_rms_dps: float) -> None:
    """At least one whole pass of the programme: every scheduled rate found as a plateau, and
    real SocketCAN with every piece in its own process calibrates as well as the same sensor and
    table on the in-process bus (within the grid's 1.3×)."""
    assert report["plateaus"] >= len(RATES)
    assert report["rates"] == len(RATES)
    assert report["held_out"]["rms_dps"] <= 1.3 * in_process_rms_dps


@pytest.mark.parametrize("cell", list(CELLS))
def test_virtual_bus_record_then_calibrate(cell, tmp_path):
    """One pass, deterministic: the recorder listens before the emulator sends its first sample."""
    r = bus_cell(cell, CELLS[cell][1], tmp_path, rates=RATES, dwell_s=DWELL_S, fs_hz=50.0, seed=0)
    assert r.found == r.scheduled == len(RATES) + 1  # a pass ends at rest
    assert r.rates_ok
    assert r.ramp_samples_used == 0
    assert r.held_out_rms_dps < 0.05


def _pass_s(b: TableBehaviour) -> float:
    from canical.sim.table_recording import schedule

    return float(schedule(np.array([*RATES, 0.0]), DWELL_S, b, initial_dps=0.0).stop[-1])


@pytest.mark.vcan
@pytest.mark.parametrize("cell", list(CELLS))
def test_vcan_emulate_record_calibrate(cell, vcan_channel: str, tmp_path: Path):
    options = CELLS[cell][0]
    speed = 4.0
    record_s = 2.2 * _pass_s(CELLS[cell][1]) / speed
    rates = ",".join(f"{r:g}" for r in RATES)
    emulate = subprocess.Popen(
        [sys.executable, "-m", "canical", "emulate", "--interface", "socketcan", "--channel", vcan_channel,
         "--state", str(tmp_path / "state.json"), "--rate", "50", "--speed", str(speed),
         f"--table-rates={rates}", "--dwell", str(DWELL_S), *options],
        stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        assert emulate.stdout is not None
        ready = emulate.stdout.readline()
        assert ready.startswith("ready"), (ready, emulate.poll() is not None and emulate.communicate())
        log = tmp_path / "table.log"
        rec = subprocess.run(
            [sys.executable, "-m", "canical", "record", "-o", str(log), "--interface", "socketcan",
             "--channel", vcan_channel, "--dbc", str(DBC), "--duration", f"{record_s:.1f}"],
            capture_output=True, text=True, timeout=record_s + 120, check=False)
        assert rec.returncode == 0, rec.stderr
    finally:
        emulate.terminate()
        emulate.communicate(timeout=30)
    in_process = bus_cell(cell, CELLS[cell][1], tmp_path / "in-process", rates=RATES, dwell_s=DWELL_S,
                          fs_hz=50.0, seed=0)
    _check(_calibrate(log, tmp_path), in_process.held_out_rms_dps)
