"""``canical serve`` imports what it runs and nothing else: no fitting, plotting or simulation code.

Each import costs start-up time and resident memory on a small vehicle computer, for the whole
life of the daemon. The check runs the real command (a fresh interpreter, python-can's in-process
``virtual`` bus) up to READY and looks at what it has imported by then.
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

from support.daemon_fixtures import write_config, write_sets

#: Heavy or unrelated to correcting frames: present in the package, never needed by the daemon.
NOT_FOR_SERVE = (
    "matplotlib",
    "scipy",
    "canical.calibration.pipeline",
    "canical.closed_loop.search",
    "canical.calibrate.model_fit",
    "canical.calibrate.model_selection",
    "canical.calibrate.cross_validation",
    "canical.closed_loop.candidates",
    "canical.report.plots",
    "canical.report.markdown",
    "canical.sim",
    "canical.sessions.csv_file",
    "canical.sessions.canlog",
    "canical.calibration.evaluation",
    "canical.device.emulated_imu",
)

PROBE = """
import sys, threading
from canical.commands import cli
from canical.bus.daemon import Daemon
ready = Daemon.run
def run(self):
    self.notifier.ready = lambda *a: (print(" ".join(sorted(sys.modules))), self.request_stop())
    return ready(self)
Daemon.run = run
sys.exit(cli.main(["serve", "--config", sys.argv[1]]))
"""


def test_serve_imports_no_fitting_plotting_or_simulation(tmp_path: Path) -> None:
    write_sets(tmp_path)
    config = write_config(tmp_path, "bench", interface="virtual")
    out = subprocess.run([sys.executable, "-c", PROBE, str(config)], capture_output=True, text=True,
                         timeout=120, check=True).stdout
    modules = set(out.split())
    assert "canical.bus.daemon" in modules and "canical.frames.compiler" in modules
    loaded = sorted(m for m in modules if any(m == n or m.startswith(n + ".") for n in NOT_FOR_SERVE))
    assert not loaded, f"canical serve imported {loaded}"
