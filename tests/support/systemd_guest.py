"""The systemd test tier's two halves: packages built on the host, systemctl used in the guest.

Host side (:func:`prepare_packages`, called by the vcan plugin before the systemd guest boots):
the guest has no network, so the canical wheel is built here (``pip wheel --no-deps``) and the
wheels of its dependencies are fetched into a cache (``pip download``, for the guest's system
Python) that the guest's ``canical install-service --no-index --find-links`` installs from.

Guest side: thin wrappers over ``systemctl``/``journalctl`` for tests that run under the
guest's own systemd (``@pytest.mark.systemd_guest``), with drop-ins under ``/run`` so nothing
outlives the guest.
"""

from __future__ import annotations

import os
import subprocess
import sys
import time
from collections.abc import Callable
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
#: Environment variables telling the guest's tests where the packages are.
ENV_WHEEL = "CANICAL_TEST_WHEEL"
ENV_WHEELHOUSE = "CANICAL_TEST_WHEELHOUSE"
SYSTEM_PYTHON = Path("/usr/bin/python3")


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base, "canical", "wheelhouse")


def prepare_packages(run_dir: Path) -> dict[str, str]:
    """Build the wheel into ``run_dir`` and fill the dependency wheelhouse; the env for the guest.

    The wheelhouse is cached across runs (``pip download`` only fetches what is missing); a
    machine without network still works once it is filled.
    """
    wheel_dir = run_dir / "wheel"
    pip = [sys.executable, "-m", "pip", "--disable-pip-version-check", "-q"]
    proc = subprocess.run([*pip, "wheel", "--no-deps", "-w", str(wheel_dir), str(ROOT)],
                          capture_output=True, text=True, timeout=600, check=False)
    if proc.returncode != 0:
        raise RuntimeError(f"pip wheel failed:\n{proc.stdout}{proc.stderr}")
    wheel = next(wheel_dir.glob("canical-*.whl"))
    house = _cache_dir()
    house.mkdir(parents=True, exist_ok=True)
    version = subprocess.run([str(SYSTEM_PYTHON), "-c",
                              "import sys; print(f'{sys.version_info[0]}.{sys.version_info[1]}')"],
                             capture_output=True, text=True, check=False).stdout.strip() or "3"
    fetch = [*pip, "download", "--only-binary=:all:", "--python-version", version,
             "--find-links", str(house), "-d", str(house), str(wheel)]
    # The cache first (no network, seconds); the package index only for what it lacks.
    proc = subprocess.run([*fetch[:4], "--no-index", *fetch[4:]], capture_output=True, text=True,
                          timeout=300, check=False)
    if proc.returncode != 0:
        proc = subprocess.run(fetch, capture_output=True, text=True, timeout=900, check=False)
        if proc.returncode != 0:
            raise RuntimeError(f"pip download of canical's dependencies failed:\n{proc.stderr}")
    for stale in house.glob("canical-*.whl"):  # the wheel under test comes from wheel_dir only
        stale.unlink()
    return {ENV_WHEEL: str(wheel), ENV_WHEELHOUSE: str(house)}


# --------------------------------------------------------------------------------------------
# In the guest
# --------------------------------------------------------------------------------------------


def run(*argv: str, check: bool = True, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    """Run a command; on failure (with ``check``) the assertion shows its output."""
    proc = subprocess.run(list(argv), capture_output=True, text=True, timeout=timeout, check=False)
    if check:
        assert proc.returncode == 0, f"{' '.join(argv)} -> {proc.returncode}\n{proc.stdout}{proc.stderr}"
    return proc


def systemctl(*args: str, check: bool = True, timeout: float = 120) -> subprocess.CompletedProcess[str]:
    return run("systemctl", "--no-pager", *args, check=check, timeout=timeout)


def show(unit: str, *props: str) -> dict[str, str]:
    """``systemctl show`` properties of ``unit`` as a dict."""
    out = systemctl("show", unit, *(f"--property={p}" for p in props)).stdout
    return dict(line.split("=", 1) for line in out.splitlines() if "=" in line)


def wait_until(what: str, predicate: Callable[[], object], timeout: float, step: float = 0.1) -> object:
    """Poll ``predicate`` until it returns something true; fail naming ``what``."""
    end = time.monotonic() + timeout
    while True:
        value = predicate()
        if value:
            return value
        if time.monotonic() > end:
            raise AssertionError(f"timed out after {timeout} s waiting for {what}")
        time.sleep(step)


def journal(unit: str) -> list[str]:
    """The unit's journal lines (systemd's about it and its own output), message text only."""
    return run("journalctl", "--no-pager", "-o", "cat", "-u", unit).stdout.splitlines()


def drop_in(unit: str, name: str, text: str) -> Path:
    """A runtime drop-in (``/run/systemd/system/UNIT.d/NAME.conf``), then daemon-reload."""
    folder = Path("/run/systemd/system") / f"{unit}.d"
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / f"{name}.conf"
    path.write_text(text)
    systemctl("daemon-reload")
    return path


def remove_drop_ins(*units: str) -> None:
    changed = False
    for unit in units:
        folder = Path("/run/systemd/system") / f"{unit}.d"
        for path in folder.glob("*.conf"):
            path.unlink()
            changed = True
    if changed:
        systemctl("daemon-reload")
