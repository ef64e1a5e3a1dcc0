"""Install canical as a systemd service where the service's sandbox can see it.

The units run ``canical`` as a dynamic user with ``ProtectHome=``, ``PrivateTmp=`` and a
read-only system: a virtualenv under ``/tmp``, ``/root`` or ``/home`` (or a pyenv interpreter
there) is invisible to it. So the install is a venv under ``/opt/canical`` on the system
Python, ``/usr/local/bin/canical`` pointing into it (the path the units name), ``/etc/canical``
with the DBC, the daemon configuration and the coefficient sets, and the units in
``/etc/systemd/system``; everything world-readable (the dynamic user owns nothing).

Each step is planned from what is on disk and only what differs is done, so running it again
changes nothing; ``dry_run`` prints the plan and touches nothing. An operator's configuration
(``<channel>.yaml``, ``<channel>.env``) is written only when missing: it is theirs to edit.
"""

from __future__ import annotations

import os
import shlex
import subprocess
from collections.abc import Callable, Sequence
from dataclasses import dataclass, field
from importlib import resources
from pathlib import Path

from canical.errors import CanicalError
from canical.files.atomic_file import atomic_writer

UNITS = ("canical@.service", "canical-can@.service", "canical-imu-emulator@.service")
EXAMPLE_CONFIG = "canical-can0.yaml"
#: Directories the service's sandbox hides (PrivateTmp=, ProtectHome=): nothing may live there.
HIDDEN_FROM_SERVICE = ("/tmp", "/var/tmp", "/root", "/home", "/run/user")


@dataclass(frozen=True)
class Layout:
    """Where everything goes; the defaults are what the shipped units name."""

    prefix: Path = Path("/opt/canical")
    etc: Path = Path("/etc/canical")
    bin_link: Path = Path("/usr/local/bin/canical")
    unit_dir: Path = Path("/etc/systemd/system")
    python: Path = Path("/usr/bin/python3")

    @property
    def venv(self) -> Path:
        return self.prefix / "venv"


@dataclass(frozen=True)
class Request:
    """What to install: the package (a wheel or a requirement) and the vehicle's files."""

    package: str  # a wheel path, or a pip requirement such as canical==0.1.0
    channel: str = "can0"
    sets: tuple[Path, ...] = ()
    bitrate: int | None = None
    find_links: tuple[Path, ...] = ()
    no_index: bool = False


@dataclass
class Step:
    """One change: what it does (for the plan), and the action."""

    what: str
    run: Callable[[], None] = field(repr=False)


def _data(name: str) -> bytes:
    return resources.files("canical").joinpath("data", "install", name).read_bytes()


def _dbc() -> bytes:
    return resources.files("canical").joinpath("data", "canical.dbc").read_bytes()


def _differs(path: Path, content: bytes, mode: int) -> bool:
    try:
        return path.read_bytes() != content or (path.stat().st_mode & 0o777) != mode
    except OSError:
        return True


def _write(path: Path, content: bytes, mode: int = 0o644) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    with atomic_writer(path, "wb") as handle:
        handle.write(content)
    path.chmod(mode)


def _run(argv: Sequence[str]) -> None:
    proc = subprocess.run(list(argv), capture_output=True, text=True, check=False)
    if proc.returncode != 0:
        detail = (proc.stderr or proc.stdout).strip().splitlines()
        raise CanicalError(f"{shlex.join(argv)} failed (exit {proc.returncode}): "
                           f"{detail[-1] if detail else 'no output'}")


def _installed_version(venv: Path) -> str | None:
    """The canical version in the venv, read from its metadata (without importing it)."""
    for meta in sorted(venv.glob("lib/python*/site-packages/canical-*.dist-info/METADATA")):
        for line in meta.read_text(errors="replace").splitlines():
            if line.startswith("Version:"):
                return line.split(":", 1)[1].strip()
    return None


def _wheel_version(package: str) -> str | None:
    """``canical-0.1.0-py3-none-any.whl`` -> ``0.1.0``; None for a requirement."""
    name = Path(package).name
    if name.endswith(".whl") and name.count("-") >= 4:
        return name.split("-")[1]
    return None


def check_visible(path: Path, what: str) -> None:
    """Refuse a location the service's sandbox cannot see."""
    resolved = path.resolve() if path.exists() else path.absolute()
    for hidden in HIDDEN_FROM_SERVICE:
        if resolved == Path(hidden) or Path(hidden) in resolved.parents:
            raise CanicalError(f"{what} {path}: under {hidden}, which the service's sandbox hides "
                               "(PrivateTmp=, ProtectHome=); use a path like /opt/canical")


def plan(layout: Layout, request: Request) -> list[Step]:
    """The changes needed to reach the installed state; empty when it is already reached."""
    check_visible(layout.prefix, "--prefix")
    check_visible(layout.python, "--python")
    if not layout.python.is_file():
        raise CanicalError(f"--python {layout.python}: no such interpreter (apt-get install python3-venv)")
    wheel_version = _wheel_version(request.package)
    if wheel_version is not None and not Path(request.package).is_file():
        raise CanicalError(f"--wheel {request.package}: file not found")
    sets = []
    for path in request.sets:
        from canical.sets import coefficient_file  # numpy, yaml: not for install-service --help

        cset = coefficient_file.load(path)  # refuses a broken set with one line
        sets.append((path, cset.axis))
    axes = [axis for _, axis in sets]
    if len(set(axes)) != len(axes):
        raise CanicalError(f"--set: two sets for the same axis ({', '.join(axes)})")

    steps: list[Step] = []
    venv_python = layout.venv / "bin" / "python"
    if not venv_python.exists():
        steps.append(Step(f"create venv {layout.venv} on {layout.python}",
                          lambda: _run([str(layout.python), "-m", "venv", str(layout.venv)])))
    installed = None if not venv_python.exists() else _installed_version(layout.venv)
    wanted = wheel_version or (request.package.split("==", 1)[1] if "==" in request.package else None)
    if installed is None or (wanted is not None and installed != wanted):
        pip = [str(venv_python), "-m", "pip", "install", "--disable-pip-version-check", "-q"]
        if request.no_index:
            pip.append("--no-index")
        for links in request.find_links:
            pip += ["--find-links", str(links)]
        package = str(Path(request.package).absolute()) if wheel_version else request.package
        steps.append(Step(f"install {package} into {layout.venv}", lambda: _run([*pip, package])))

    target = layout.venv / "bin" / "canical"
    if not (layout.bin_link.is_symlink() and Path(os.readlink(layout.bin_link)) == target):
        def link() -> None:
            layout.bin_link.parent.mkdir(parents=True, exist_ok=True)
            tmp = layout.bin_link.with_name(f".{layout.bin_link.name}.tmp")
            tmp.unlink(missing_ok=True)
            tmp.symlink_to(target)
            os.replace(tmp, layout.bin_link)
        steps.append(Step(f"link {layout.bin_link} -> {target}", link))

    def put(path: Path, content: bytes, why: str, *, keep_existing: bool = False) -> None:
        if (keep_existing and path.exists()) or not _differs(path, content, 0o644):
            return
        steps.append(Step(f"write {path} ({why})", lambda: _write(path, content)))

    if not layout.etc.is_dir() or (layout.etc.stat().st_mode & 0o777) != 0o755:
        steps.append(Step(f"create {layout.etc} (mode 755)", lambda: _mkdir_readable(layout.etc)))
    put(layout.etc / "canical.dbc", _dbc(), "frame layouts of this canical")
    config = _data(EXAMPLE_CONFIG).decode().replace("channel: can0", f"channel: {request.channel}")
    put(layout.etc / f"{request.channel}.yaml", config.encode(), "daemon configuration, if missing",
        keep_existing=True)
    for path, axis in sets:
        put(layout.etc / f"imu-{axis}.yaml", path.read_bytes(), f"axis {axis} set from {path}")
    if request.bitrate is not None:
        env = f"BITRATE={request.bitrate}\nRESTART_MS=100\n".encode()
        put(layout.etc / f"{request.channel}.env", env, "bit timing for canical-can@, if missing",
            keep_existing=True)

    units_changed = False
    for unit in UNITS:
        content = _data(unit)
        path = layout.unit_dir / unit
        if _differs(path, content, 0o644):
            units_changed = True
            put(path, content, "unit")
    if units_changed and Path("/run/systemd/system").is_dir():
        steps.append(Step("systemctl daemon-reload", lambda: _run(["systemctl", "daemon-reload"])))
    return steps


def _mkdir_readable(path: Path) -> None:
    path.mkdir(parents=True, exist_ok=True)
    path.chmod(0o755)


def install(layout: Layout, request: Request, *, dry_run: bool = False,
            out: Callable[[str], None] = print) -> int:
    """Carry out (or with ``dry_run`` only print) the plan; returns the number of steps."""
    steps = plan(layout, request)
    if not steps:
        out("canical service: already installed, nothing to do")
        return 0
    old_umask = os.umask(0o022)  # the dynamic user must be able to read every installed file
    try:
        for step in steps:
            out(("would " if dry_run else "") + step.what)
            if not dry_run:
                step.run()
    finally:
        os.umask(old_umask)
    return len(steps)
