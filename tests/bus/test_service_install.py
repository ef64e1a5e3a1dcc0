"""``canical install-service`` on the host: what it refuses and what a dry run plans.

The real install (from a built wheel, then the units started from it) runs under systemd in
the guest: tests/bus/test_systemd_guest.py::test_install_service_from_wheel.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

from canical.bus.service_install import Layout, Request, plan
from canical.errors import CanicalError


def _canical(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "canical", "install-service", *args],
                          capture_output=True, text=True, timeout=120, check=False)


@pytest.mark.parametrize(("option", "value", "hidden"), [
    ("--prefix", "/tmp/canical", "/tmp"),
    ("--prefix", "/home/ops/canical", "/home"),
    ("--python", "/root/.pyenv/versions/3.11.7/bin/python3", "/root"),
])
def test_refuses_what_the_sandbox_hides(option: str, value: str, hidden: str) -> None:
    proc = _canical(option, value, "--dry-run")
    assert proc.returncode == 2
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr
    assert f"{option} {value}: under {hidden}, which the service's sandbox hides" in proc.stderr


def test_dry_run_plans_everything_and_touches_nothing(tmp_path: Path) -> None:
    base = Path("/opt") / f"canical-test-{os.getpid()}"  # visible to a service, never created
    proc = _canical("--dry-run", "--prefix", str(base), "--etc", str(base / "etc"),
                    "--bin-link", str(base / "bin" / "canical"), "--unit-dir", str(base / "units"),
                    "--channel", "can1", "--bitrate", "500000")
    assert proc.returncode == 0, proc.stderr
    lines = proc.stdout.splitlines()
    assert all(line.startswith("would ") for line in lines), lines
    assert lines[:3] == [f"would create venv {base}/venv on /usr/bin/python3",
                         f"would install canical==0.1.0 into {base}/venv",
                         f"would link {base}/bin/canical -> {base}/venv/bin/canical"]
    for name in ("etc/canical.dbc", "etc/can1.yaml", "etc/can1.env", "units/canical@.service",
                 "units/canical-can@.service", "units/canical-imu-emulator@.service"):
        assert any(line.startswith(f"would write {base}/{name} ") for line in lines), name
    assert not base.exists()


def test_a_broken_set_is_refused_before_anything_happens(tmp_path: Path) -> None:
    bad = tmp_path / "imu-x.yaml"
    bad.write_text("model: {kind: nonsense}\n")
    with pytest.raises(CanicalError) as info:
        plan(Layout(prefix=Path("/opt/canical-never")), Request(package="canical", sets=(bad,)))
    assert str(bad) in str(info.value)
