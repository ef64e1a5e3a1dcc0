"""The systemd units as systemd itself judges them: ``verify`` clean, exposure kept low.

The templates are checked as concrete instances (``canical@can0.service``) with ExecStart
pointed at the canical this test suite runs (verify insists the binary exists).
"""

from __future__ import annotations

import re
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
UNITS = ROOT / "systemd"
#: Every unit canical ships, by template name, with the folder it lives in.
TEMPLATES = {"canical@.service": UNITS, "canical-can@.service": UNITS,
             "canical-imu-emulator@.service": ROOT / "services"}
#: Exposure levels reached (systemd-analyze security --offline=yes); lower is better, 10 is worst.
MAX_EXPOSURE = {"canical@can0.service": 0.8, "canical-can@can0.service": 2.0,
                "canical-imu-emulator@can0.service": 0.8}


def _canical_binary() -> str:
    beside = Path(sys.executable).parent / "canical"
    found = str(beside) if beside.is_file() else shutil.which("canical")
    assert found, "canical is not installed (pip install -e .)"
    return found


@pytest.fixture(scope="module")
def instances(tmp_path_factory: pytest.TempPathFactory) -> Path:
    assert shutil.which("systemd-analyze"), "systemd-analyze missing: apt-get install systemd"
    folder = tmp_path_factory.mktemp("units")
    for template, folder_in in TEMPLATES.items():
        text = (folder_in / template).read_text().replace("/usr/local/bin/canical", _canical_binary())
        (folder / template.replace("@", "@can0")).write_text(text)
    return folder


def _analyze(folder: Path, *args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run(["systemd-analyze", *args], cwd=folder, capture_output=True, text=True,
                          timeout=120, check=False)


def test_units_verify_clean(instances: Path) -> None:
    proc = _analyze(instances, "verify", "--man=no", *(f"./{u}" for u in MAX_EXPOSURE))
    assert proc.returncode == 0 and not proc.stderr.strip() and not proc.stdout.strip(), (
        proc.stdout + proc.stderr)


@pytest.mark.parametrize("unit", sorted(MAX_EXPOSURE))
def test_unit_exposure_level(instances: Path, unit: str) -> None:
    proc = _analyze(instances, "security", "--offline=yes", f"./{unit}")
    found = re.search(r"Overall exposure level for \S+: ([0-9.]+)", proc.stdout)
    assert found, proc.stdout + proc.stderr
    level = float(found.group(1))
    print(f"{unit}: exposure {level}")
    assert level <= MAX_EXPOSURE[unit], proc.stdout


def test_daemon_unit_is_notify_with_watchdog_unprivileged() -> None:
    """The properties the daemon's code relies on are set in the unit."""
    text = (UNITS / "canical@.service").read_text()
    for line in ("Type=notify", "WatchdogSec=", "DynamicUser=yes", "CapabilityBoundingSet=\n",
                 "RestrictAddressFamilies=AF_CAN AF_UNIX", "NoNewPrivileges=yes", "ProtectSystem=strict",
                 "ExecReload=/bin/kill -HUP $MAINPID", "--channel %i",
                 "StateDirectory=canical\n"):  # /var/lib/canical: field_log and state_file go there
        assert line in text, line


def test_no_unit_waits_for_a_device_unit() -> None:
    """Device units exist only where udev runs; a dependency on one hangs 90 s elsewhere."""
    for template, folder in TEMPLATES.items():
        settings = [line for line in (folder / template).read_text().splitlines()
                    if not line.startswith("#")]
        assert not any("sys-subsystem-net-devices" in line for line in settings), template


def test_interface_unit_sets_bit_timing_only_when_configured() -> None:
    """vcan has no bit timing ("Operation not supported"): only a BITRATE from the .env sets it."""
    text = (UNITS / "canical-can@.service").read_text()
    assert "Environment=BITRATE= " in text and "EnvironmentFile=-/etc/canical/%i.env" in text
    assert 'if [ -n "$BITRATE" ]; then' in text
