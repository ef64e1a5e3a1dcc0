"""Run code against a real SocketCAN ``vcan`` interface, even on a kernel without SocketCAN.

Why this exists: the development and CI machines run a kernel built without ``CONFIG_CAN``
(``ip link add vcan0 type vcan`` fails, ``socket(AF_CAN)`` gives EAFNOSUPPORT), there is no
working KVM and no Docker engine. Mocking the bus would not exercise the kernel's CAN stack
(receive filters, loopback, socket semantics) that the service relies on in production. What
does work is User-mode Linux (Debian's ``user-mode-linux`` package): a Linux kernel running as
an ordinary process that ships the CAN modules. Booted with the host's ``/`` as a read-only
``hostfs`` root file system under an overlay, the guest sees the same files, Python
interpreter and site-packages, so a command can be run "as if on the host", just with
``vcan0``/``vcan1`` available.

This module is deliberately free of ``canical`` and pytest imports so it can be used from
scripts and from the pytest plugin (``tests/support/vcan_plugin.py``) alike. It provides:

* :func:`host_vcan_status` - does the host itself have a usable ``vcan0``?
* :func:`locate_uml` - find ``linux.uml``, its CAN modules and the guest tools.
* :func:`run_in_uml` - run a command in a UML guest with ``vcan0`` and ``vcan1`` up, either
  from a shell init or under the host's own systemd booted as the guest's PID 1.

A guest never changes the host: the kernel mounts the host's ``/`` read-only and the init script
stacks an overlay with a tmpfs upper layer on it; only the run dir is mounted writable.

One host quirk is handled here as well: the bookworm UML kernel (6.1) exchanges the FPU state
with its guest processes through ``PTRACE_{GET,SET}REGSET(NT_X86_XSTATE)`` using a fixed
832-byte buffer, but hosts with AVX-512/AMX have a far larger XSAVE area and the host kernel
refuses a short SETREGSET with EFAULT: init dies at once ("ptrace set fp regs failed,
errno = 14"). A tiny ``LD_PRELOAD`` shim (:data:`XSTATE_SHIM_SOURCE`, compiled on first use
with the system C compiler and cached) pads those calls to the host's full XSAVE size while
keeping each guest task's upper vector state, so AVX-512 code (glibc's string functions,
NumPy) stays correct inside the guest.
"""

from __future__ import annotations

import contextlib
import errno
import hashlib
import os
import re
import shlex
import shutil
import signal
import socket
import subprocess
import sys
import tempfile
import time
from collections.abc import Mapping, Sequence
from dataclasses import dataclass
from pathlib import Path

#: The apt packages that provide the kernel (``linux.uml``) and ``insmod`` used in the guest.
INSTALL_HINT = "install user-mode-linux and kmod: apt-get install user-mode-linux kmod"

#: Environment variable set to ``1`` inside the guest, so code can tell where it runs.
ENV_IN_UML = "CANICAL_IN_UML"
#: Environment variable holding the guest's run directory (on the shared file system).
ENV_RUN_DIR = "CANICAL_UML_RUN_DIR"
#: Overrides for unusual installations.
ENV_KERNEL = "CANICAL_UML_KERNEL"
ENV_MODULES = "CANICAL_UML_MODULES"
ENV_MEM = "CANICAL_UML_MEM"
#: Set to ``1`` for a command that runs under the guest's own systemd (``run_in_uml(systemd=True)``).
ENV_IN_SYSTEMD = "CANICAL_IN_SYSTEMD_GUEST"

#: The vcan interfaces every guest brings up.
GUEST_CHANNELS: tuple[str, ...] = ("vcan0", "vcan1")

#: Kernel modules to load, in dependency order, relative to ``<module dir>/kernel``.
#: ``vcan`` needs ``can-dev``; the protocol modules need ``can``.
CAN_MODULES: tuple[str, ...] = (
    "net/can/can.ko",
    "net/can/can-raw.ko",
    "net/can/can-bcm.ko",
    "drivers/net/can/dev/can-dev.ko",
    "drivers/net/can/vcan.ko",
)

#: Default overall time limit for one guest run (boot + command), in seconds.
DEFAULT_TIMEOUT = 1800.0  # the whole vcan tier runs in one guest: ~8 min today, CI allows 90

_ARPHRD_CAN = 280
_IFF_UP = 0x1
_SYSTEM_PATH = "/usr/local/sbin:/usr/local/bin:/usr/sbin:/usr/bin:/sbin:/bin"
_ENV_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]*\Z")
# Host variables that must not leak into the guest: they describe the host process (pytest's
# current test, xdist worker) or would redirect the guest's temporary files back to the host's.
_DROP_ENV = frozenset({"PYTEST_CURRENT_TEST", "PYTEST_XDIST_WORKER", "PYTEST_XDIST_WORKER_COUNT",
                       "TMPDIR", "TMP", "TEMP"})


class UmlUnavailable(RuntimeError):
    """User-mode Linux (or a piece the guest needs) is not installed on this machine."""


# --------------------------------------------------------------------------------------------
# (a) Host SocketCAN detection
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class HostVcanStatus:
    """Whether the host kernel can be used directly, and why not if it can't."""

    usable: bool
    reason: str
    channels: tuple[str, ...] = ()


def _read_sys(ifname: str, attr: str) -> str | None:
    """Read ``/sys/class/net/<ifname>/<attr>``; None when the interface does not exist."""
    try:
        return Path("/sys/class/net", ifname, attr).read_text().strip()
    except OSError:
        return None


def _try_create_vcan(ifname: str) -> None:
    """Best effort: create and raise ``ifname`` as root; failures show up in the later probe."""
    if os.geteuid() != 0 or shutil.which("ip") is None:
        return

    def quiet(*cmd: str) -> None:
        with contextlib.suppress(OSError, subprocess.SubprocessError):
            subprocess.run(cmd, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, timeout=10,
                           check=False)

    if _read_sys(ifname, "type") is None:
        if shutil.which("modprobe"):
            quiet("modprobe", "vcan")
        quiet("ip", "link", "add", "dev", ifname, "type", "vcan")
    quiet("ip", "link", "set", ifname, "up")


def probe_can_interface(ifname: str) -> str | None:
    """Return None if ``ifname`` is an up CAN interface a raw socket can bind, else why not."""
    if _read_sys(ifname, "type") is None:
        return f"no network interface {ifname!r}"
    if _read_sys(ifname, "type") != str(_ARPHRD_CAN):
        return f"{ifname!r} is not a CAN interface"
    flags = _read_sys(ifname, "flags") or "0"
    if not int(flags, 16) & _IFF_UP:
        return f"{ifname!r} is down"
    try:
        with socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW) as sock:
            sock.bind((ifname,))
    except OSError as exc:
        return f"cannot bind a CAN_RAW socket to {ifname!r}: {exc}"
    return None


def host_vcan_status(channels: Sequence[str] = GUEST_CHANNELS, *,
                     create: bool = True) -> HostVcanStatus:
    """Tell whether this kernel offers SocketCAN with (at least) the first of ``channels`` up.

    With ``create`` and root rights, missing interfaces are created with ``ip link add``
    first, as a CI job on a SocketCAN-capable kernel would want.
    """
    if not hasattr(socket, "AF_CAN"):
        return HostVcanStatus(False, "this Python has no socket.AF_CAN")
    try:
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW).close()
    except OSError as exc:
        detail = "EAFNOSUPPORT" if exc.errno == errno.EAFNOSUPPORT else str(exc)
        return HostVcanStatus(False, f"host kernel has no SocketCAN (socket(AF_CAN): {detail})")
    usable: list[str] = []
    problems: list[str] = []
    for ifname in channels:
        if create and probe_can_interface(ifname) is not None:
            _try_create_vcan(ifname)
        problem = probe_can_interface(ifname)
        if problem is None:
            usable.append(ifname)
        else:
            problems.append(problem)
    if not channels or channels[0] not in usable:
        return HostVcanStatus(False, "; ".join(problems) or "no channel requested", tuple(usable))
    return HostVcanStatus(True, "host SocketCAN with " + ", ".join(usable), tuple(usable))


# --------------------------------------------------------------------------------------------
# (b) Locating User-mode Linux
# --------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class UmlInstallation:
    """Everything needed to boot a guest with vcan: kernel, its modules and guest tools."""

    kernel: Path
    module_dir: Path
    insmod: Path
    ip: Path


def _find_tool(name: str) -> Path | None:
    """Find a system tool even when /sbin is not on the caller's PATH."""
    found = shutil.which(name, path=os.pathsep.join([os.environ.get("PATH", ""), _SYSTEM_PATH]))
    return Path(found) if found else None


def _kernel_version(kernel: Path) -> str | None:
    """Ask ``linux.uml --version`` for its release (it prints e.g. ``6.1.176``)."""
    try:
        out = subprocess.run([str(kernel), "--version"], capture_output=True, text=True,
                             timeout=30, check=False, stdin=subprocess.DEVNULL).stdout
    except (OSError, subprocess.SubprocessError):
        return None
    words = out.split()
    return words[0] if words else None


def locate_uml() -> UmlInstallation:
    """Find ``linux.uml`` and its CAN modules, or raise :class:`UmlUnavailable` saying how to fix.

    ``$CANICAL_UML_KERNEL`` and ``$CANICAL_UML_MODULES`` (the directory holding ``kernel/``)
    override the Debian locations.
    """
    kernel_env = os.environ.get(ENV_KERNEL)
    kernel_str = kernel_env or shutil.which("linux.uml") or "/usr/bin/linux.uml"
    kernel = Path(kernel_str)
    if not (kernel.is_file() and os.access(kernel, os.X_OK)):
        where = f"${ENV_KERNEL}={kernel_env}" if kernel_env else "linux.uml"
        raise UmlUnavailable(f"User-mode Linux kernel not found ({where}); {INSTALL_HINT}")

    vcan_ko = Path("kernel", CAN_MODULES[-1])
    if modules_env := os.environ.get(ENV_MODULES):
        module_dir = Path(modules_env)
    else:
        candidates = sorted(p for p in Path("/usr/lib/uml/modules").glob("*")
                            if (p / vcan_ko).is_file())
        version = _kernel_version(kernel)
        matching = [p for p in candidates if p.name == version]
        if not (matching or candidates):
            raise UmlUnavailable(f"no UML CAN modules under /usr/lib/uml/modules; {INSTALL_HINT}")
        module_dir = (matching or candidates)[-1]
    missing = [m for m in CAN_MODULES if not (module_dir / "kernel" / m).is_file()]
    if missing:
        raise UmlUnavailable(f"UML module dir {module_dir} lacks {', '.join(missing)}; "
                             f"{INSTALL_HINT}")

    insmod = _find_tool("insmod")
    ip = _find_tool("ip")
    if insmod is None:
        raise UmlUnavailable(f"insmod not found (needed inside the guest); {INSTALL_HINT}")
    if ip is None:
        raise UmlUnavailable("ip not found (needed inside the guest); apt-get install iproute2")
    return UmlInstallation(kernel=kernel, module_dir=module_dir, insmod=insmod, ip=ip)


def uml_unavailable_reason() -> str | None:
    """None if a guest can be booted here, else the human-readable reason it cannot."""
    try:
        locate_uml()
    except UmlUnavailable as exc:
        return str(exc)
    return None


# --------------------------------------------------------------------------------------------
# The XSAVE-size shim (see the module docstring)
# --------------------------------------------------------------------------------------------

XSTATE_SHIM_SOURCE = r"""
/* LD_PRELOAD shim for linux.uml (6.1) on hosts whose XSAVE area is larger than UML's buffer.
 * GETREGSET(NT_X86_XSTATE): read the full area, hand UML the prefix it asked for, and keep the
 * full copy keyed by UML's buffer address (one buffer per guest task).
 * SETREGSET(NT_X86_XSTATE): the host insists on the full size, so overlay UML's prefix on the
 * copy kept for that buffer (or on the process's current state) and set that. */
#define _GNU_SOURCE
#include <dlfcn.h>
#include <elf.h>
#include <stdarg.h>
#include <string.h>
#include <sys/mman.h>
#include <sys/ptrace.h>
#include <sys/types.h>
#include <sys/uio.h>

#define MAX_XSTATE (64 * 1024)
#define SLOTS 4096

typedef long (*ptrace_fn)(int, pid_t, void *, void *);
static ptrace_fn real_ptrace;
static unsigned char tmp[MAX_XSTATE]; /* static: UML calls this on small kernel stacks */
static void *keys[SLOTS];
static size_t full_size;
static unsigned char *pool;

__attribute__((constructor)) static void init(void) {
    real_ptrace = (ptrace_fn)dlsym(RTLD_NEXT, "ptrace");
}

static unsigned char *slot_for(void *key, int create) {
    size_t i = ((size_t)key >> 6) % SLOTS;
    if (!pool || (keys[i] != key && !create)) return NULL;
    keys[i] = key;
    return pool + i * full_size;
}

long ptrace(enum __ptrace_request request, ...) {
    va_list ap;
    va_start(ap, request);
    pid_t pid = va_arg(ap, pid_t);
    void *addr = va_arg(ap, void *);
    void *data = va_arg(ap, void *);
    va_end(ap);
    if ((request != PTRACE_GETREGSET && request != PTRACE_SETREGSET) ||
        (long)addr != NT_X86_XSTATE || data == NULL)
        return real_ptrace(request, pid, addr, data);
    struct iovec *uiov = data;
    struct iovec iov = {tmp, sizeof tmp};
    if (request == PTRACE_GETREGSET) {
        long r = real_ptrace(PTRACE_GETREGSET, pid, addr, &iov);
        if (r < 0) return r;
        if (!full_size) {
            full_size = iov.iov_len;
            void *p = mmap(NULL, SLOTS * full_size, PROT_READ | PROT_WRITE,
                           MAP_PRIVATE | MAP_ANONYMOUS | MAP_NORESERVE, -1, 0);
            if (p != MAP_FAILED) pool = p;
        }
        size_t n = iov.iov_len < uiov->iov_len ? iov.iov_len : uiov->iov_len;
        memcpy(uiov->iov_base, tmp, n);
        uiov->iov_len = n;
        unsigned char *s = iov.iov_len == full_size ? slot_for(uiov->iov_base, 1) : NULL;
        if (s) memcpy(s, tmp, full_size);
        return r;
    }
    unsigned char *s = slot_for(uiov->iov_base, 0);
    if (s) {
        memcpy(tmp, s, full_size);
        iov.iov_len = full_size;
    } else {
        long r = real_ptrace(PTRACE_GETREGSET, pid, addr, &iov);
        if (r < 0) return r;
    }
    if (uiov->iov_len >= iov.iov_len) return real_ptrace(request, pid, addr, data);
    memcpy(tmp, uiov->iov_base, uiov->iov_len);
    return real_ptrace(PTRACE_SETREGSET, pid, addr, &iov);
}
"""


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base, "canical")


def build_xstate_shim(cache_dir: Path | None = None) -> Path | None:
    """Compile (once, cached by source hash) the XSAVE shim; None when no C compiler exists.

    Without the shim UML still works on hosts without AVX-512; on others the guest's init
    crashes and :class:`GuestResult` points at the missing compiler.
    """
    digest = hashlib.sha256(XSTATE_SHIM_SOURCE.encode()).hexdigest()[:16]
    target_dir = cache_dir or _cache_dir()
    target = target_dir / f"uml-xstate-shim-{digest}.so"
    if target.is_file():
        return target
    compiler = os.environ.get("CC") or shutil.which("cc") or shutil.which("gcc")
    if not compiler:
        return None
    try:
        target_dir.mkdir(parents=True, exist_ok=True)
        with tempfile.TemporaryDirectory(dir=target_dir) as work:
            src = Path(work, "shim.c")
            src.write_text(XSTATE_SHIM_SOURCE)
            out = Path(work, "shim.so")
            proc = subprocess.run([compiler, "-O2", "-shared", "-fPIC", "-o", str(out), str(src),
                                   "-ldl"], capture_output=True, text=True, timeout=120,
                                  check=False)
            if proc.returncode != 0:
                raise UmlUnavailable(f"compiling the UML XSAVE shim failed:\n{proc.stderr}")
            os.replace(out, target)  # atomic: concurrent builders never see a partial file
    except OSError:
        if cache_dir is None:  # e.g. read-only HOME: build into a private temp dir instead
            return build_xstate_shim(Path(tempfile.mkdtemp(prefix="canical-uml-shim-")))
        raise
    return target


# --------------------------------------------------------------------------------------------
# (c) Running a command in a guest
# --------------------------------------------------------------------------------------------


@dataclass
class GuestResult:
    """What happened in one guest run; ``returncode`` is None if the command never finished."""

    returncode: int | None
    stdout: str
    stderr: str
    journal: str  # the systemd guest's journal, copied out when the command failed
    console: str
    run_dir: Path
    duration: float
    boot_duration: float | None
    timed_out: bool
    setup_error: str | None
    kernel_returncode: int | None

    @property
    def ok(self) -> bool:
        """True when the command ran to completion with exit status 0."""
        return self.returncode == 0

    def headline(self) -> str:
        """One line saying how the guest run ended, with its duration and run dir."""
        if self.timed_out:
            head = f"UML guest timed out after {self.duration:.0f} s and was killed"
        elif self.setup_error:
            head = f"UML guest setup failed: {self.setup_error}"
        elif self.returncode is None:
            head = (f"UML guest stopped before the command finished (kernel exit status "
                    f"{self.kernel_returncode})")
        else:
            head = f"command in UML guest exited with status {self.returncode}"
        return f"{head} [{self.duration:.1f} s; run dir {self.run_dir}]"

    def describe(self, tail: int = 4000) -> str:
        """A failure report with the tails of all guest output, for pytest and humans."""
        parts = [self.headline()]
        if "ptrace set fp regs failed" in self.console:
            parts.append("hint: the host's XSAVE area is larger than this UML kernel handles; "
                         "install a C compiler (apt-get install gcc) so the XSAVE shim builds")
        for name, text in (("stdout", self.stdout), ("stderr", self.stderr),
                           ("journal", self.journal), ("console", self.console)):
            if text.strip():
                snippet = text if len(text) <= tail else "...\n" + text[-tail:]
                parts.append(f"----- guest {name} (last {tail} chars) -----\n{snippet.rstrip()}")
        return "\n".join(parts)


def guest_environment(base: Mapping[str, str], run_dir: Path) -> dict[str, str]:
    """The environment for the guest command: the caller's, made to fit inside the guest.

    Everything is kept (PATH, VIRTUAL_ENV, PYTHONPATH, HOME, ...) so the same interpreter and
    site-packages are used, except host-process specifics; temporary files go to the run dir
    so the guest never collides with the host's own ``/tmp`` users (e.g. pytest's basetemp).
    """
    env = {k: v for k, v in base.items()
           if k not in _DROP_ENV and _ENV_NAME.match(k) and "\0" not in v}
    env.setdefault("PATH", _SYSTEM_PATH)
    tmp = str(run_dir / "tmp")
    env.update({"TMPDIR": tmp, "TMP": tmp, "TEMP": tmp, ENV_IN_UML: "1",
                ENV_RUN_DIR: str(run_dir)})
    return env


#: The overlay module, relative to ``<module dir>/kernel``: the guest's root is the host's,
#: read-only, under a tmpfs upper layer, so nothing a guest does reaches the host's files.
OVERLAY_MODULE = "fs/overlayfs/overlay.ko"
#: Inside the guest: where stage 1 assembles the new root before switching into it.
_NEWROOT = "/run/canical-root"
#: The unit that runs the command when the guest boots systemd (``systemd=True``).
GUEST_UNIT = "canical-guest-command.service"


def _guest_unit(run_dir: Path) -> str:
    """The oneshot that runs the command after multi-user.target and powers the guest off.

    ``SuccessAction=``/``FailureAction=`` belong in [Unit] (in [Service] systemd ignores them).
    """
    return "\n".join([
        "[Unit]",
        "Description=canical test command in the systemd guest",
        "After=multi-user.target",
        "SuccessAction=poweroff",
        "FailureAction=poweroff",
        "[Service]",
        "Type=oneshot",
        "TimeoutStartSec=infinity",
        f"ExecStart=/bin/sh {run_dir / 'command.sh'}",
        "StandardOutput=journal",
        "StandardError=journal",
        "",
    ])


def render_init_script(uml: UmlInstallation, run_dir: Path, command: Sequence[str], cwd: Path,
                       env: Mapping[str, str], channels: Sequence[str] = GUEST_CHANNELS, *,
                       systemd: bool = False) -> tuple[str, str]:
    """The guest's PID 1 (``init.sh``) and the script that runs the command (``command.sh``).

    PID 1 sets up an overlay root, CAN modules and vcans, then runs the command or systemd.

    The kernel mounts the host's ``/`` read-only (hostfs ``ro``); this script stacks an overlay
    with a tmpfs upper layer on it, binds only ``run_dir`` writable from the host, and
    switches into that root: the guest can write anywhere, and the host sees only ``run_dir``.
    Halting uses ``-d`` (no wtmp record, which a writable root would have put in the host's
    ``/var/log/wtmp``).

    Without ``systemd`` the command runs in the new root from this script. With it,
    ``/lib/systemd/systemd`` is exec'd as PID 1 in the new root and :data:`GUEST_UNIT` runs the
    command after ``multi-user.target``, then powers off; on failure the journal is copied to
    ``run_dir/journal.txt``. The kernel's exit status does not carry the command's, so the
    status goes to a file in the run dir; setup failures to ``setup_error`` likewise.
    """
    q = shlex.quote
    run = q(str(run_dir))
    new = _NEWROOT
    kernel_dir = uml.module_dir / "kernel"
    ip = q(str(uml.ip))
    lines = [
        "#!/bin/sh",
        "# Generated by tests/support/vcan_harness.py: PID 1 of a User-mode Linux guest.",
        f"PATH={q(_SYSTEM_PATH)}; export PATH",
        f"RUN={run}",
        f"NEW={new}",
        'stop() { sync; halt -d -f; poweroff -d -f; echo o > "$NEW/proc/sysrq-trigger";'
        ' echo o > /proc/sysrq-trigger; exit 1; }',
        # Before the run dir is mounted, a setup failure can only be told on the console.
        'fail() { echo "canical-uml: setup failed: $*"; echo "$*" > "$NEW$RUN/setup_error"; stop; }',
        "mount -t proc proc /proc || fail 'mount /proc'",
        "mount -t sysfs sysfs /sys || fail 'mount /sys'",
        # The host's / is read-only here: build the writable root on a tmpfs over /run.
        "mount -t tmpfs -o mode=755 tmpfs /run || fail 'mount tmpfs on /run'",
        f"{q(str(uml.insmod))} {q(str(kernel_dir / OVERLAY_MODULE))} || fail 'insmod overlay'",
        'mkdir -p /run/upper /run/work "$NEW"',
        'mount -t overlay overlay -o lowerdir=/,upperdir=/run/upper,workdir=/run/work "$NEW"'
        " || fail 'mount the overlay root'",
        # A container marker makes systemd think it runs in docker (and ignore systemd.unit=).
        'rm -f "$NEW/.dockerenv" "$NEW/run/.containerenv"',
        'mount --move /proc "$NEW/proc" && mount --move /sys "$NEW/sys"'
        " || fail 'move /proc and /sys'",
        'mount --move /dev "$NEW/dev" || mount -t devtmpfs devtmpfs "$NEW/dev"'
        " || fail 'mount /dev'",
        'mount -t tmpfs -o mode=755 tmpfs "$NEW/run" || fail "mount $NEW/run"',
        'mkdir -p "$NEW/dev/shm" "$NEW/dev/pts"',
        'mount -t tmpfs -o mode=1777 tmpfs "$NEW/dev/shm" || fail "mount /dev/shm"',
        'mount -t devpts devpts "$NEW/dev/pts" 2>/dev/null',
        # The run dir: the one host directory the guest writes (results, logs, temp files).
        'mkdir -p "$NEW$RUN" && mount -t hostfs hostfs -o "$RUN" "$NEW$RUN"'
        " || fail 'mount the run dir'",
        f"{ip} link set lo up",
    ]
    for module in CAN_MODULES:
        path = q(str(kernel_dir / module))
        lines.append(f"{q(str(uml.insmod))} {path} || fail {q('insmod ' + module)}")
    for ifname in channels:
        lines.append(f"{ip} link add dev {q(ifname)} type vcan && {ip} link set {q(ifname)} up"
                     f" || fail {q('creating ' + ifname)}")
    env_args = " ".join(q(f"{k}={v}") for k, v in sorted(env.items()))
    cmd = " ".join(q(c) for c in command)
    run_command = [
        f"mkdir -p {q(env['TMPDIR'])}",
        f"cd {q(str(cwd))} || {{ echo {q('cd ' + str(cwd))} > \"$RUN/setup_error\"; exit 1; }}",
        f'/usr/bin/env -i {env_args} {cmd} </dev/null >"$RUN/stdout.txt" 2>"$RUN/stderr.txt"',
        'code=$?',
        'echo $code > "$RUN/status.tmp" && mv "$RUN/status.tmp" "$RUN/status"',
    ]
    if not systemd:
        lines += [': > "$NEW$RUN/ready"', 'chroot "$NEW" /bin/sh "$RUN/command.sh"', "stop", ""]
        return "\n".join(lines), "\n".join(["#!/bin/sh", f"RUN={run}", *run_command, ""])
    unit_dir = "$NEW/etc/systemd/system"
    lines += [
        # Services the host's admin enabled (databases, ...) are not the guest's business.
        f'rm -f "{unit_dir}"/multi-user.target.wants/*',
        # systemd-tmpfiles empties /tmp at boot ("D /tmp"): in the overlay that would hide
        # the host's /tmp from the guest (a checkout or cwd there), so keep /tmp as it is.
        'mkdir -p "$NEW/etc/tmpfiles.d" && ln -sf /dev/null "$NEW/etc/tmpfiles.d/tmp.conf"',
        f'mkdir -p "{unit_dir}/multi-user.target.wants"',
        f'cp "$RUN/{GUEST_UNIT}" "{unit_dir}/{GUEST_UNIT}" || fail "install {GUEST_UNIT}"',
        f'ln -sf ../{GUEST_UNIT} "{unit_dir}/multi-user.target.wants/{GUEST_UNIT}"',
        ': > "$NEW$RUN/ready"',
        # pivot_root, not a bare chroot: in a chroot the kernel refuses new user namespaces
        # (PrivateUsers= would fail with EPERM) and systemd would see itself in a container.
        'cd "$NEW" && mkdir -p run/oldroot && pivot_root . run/oldroot || fail "pivot_root"',
        "exec chroot . /bin/sh -c 'umount -l /run/oldroot; rmdir /run/oldroot;"
        " exec /lib/systemd/systemd --system --unit=multi-user.target'",
        "",
    ]
    command_script = [
        "#!/bin/sh",
        f"RUN={run}",
        *run_command,
        # On failure, the guest's whole journal goes to the run dir for the host to read.
        '[ "$code" = 0 ] || journalctl -b --no-pager -o short-monotonic > "$RUN/journal.txt" 2>&1',
        "exit $code",
        "",
    ]
    return "\n".join(lines), "\n".join(command_script)


def _kill_group(pgid: int) -> None:
    """SIGKILL a whole process group: the UML kernel and all its per-guest-process helpers."""
    with contextlib.suppress(ProcessLookupError, PermissionError):
        os.killpg(pgid, signal.SIGKILL)


def _read(path: Path) -> str:
    try:
        return path.read_text(errors="replace")
    except OSError:
        return ""


def run_in_uml(command: Sequence[str], *, cwd: str | os.PathLike[str] | None = None,
               env: Mapping[str, str] | None = None, timeout: float = DEFAULT_TIMEOUT,
               run_dir: str | os.PathLike[str] | None = None, mem: str | None = None,
               channels: Sequence[str] = GUEST_CHANNELS, systemd: bool = False) -> GuestResult:
    """Run ``command`` inside a fresh UML guest with ``channels`` (vcan) up; wait for it.

    With ``systemd`` the guest boots the host's systemd as PID 1 and runs the command as the
    oneshot :data:`GUEST_UNIT` after ``multi-user.target`` (the command can then use
    ``systemctl``, start units and read the journal); ``CANICAL_IN_SYSTEMD_GUEST=1`` is set.

    ``cwd`` and ``env`` default to the caller's; ``CANICAL_IN_UML=1`` is added. The command's
    stdout/stderr are written to files in ``run_dir`` (created, unique, under the temp dir if
    not given; the caller owns it and may delete it) and returned. On ``timeout`` the whole UML
    process group is killed. Raises :class:`UmlUnavailable` if UML is not installed.
    """
    uml = locate_uml()
    shim = build_xstate_shim()
    rdir = Path(run_dir) if run_dir is not None else Path(tempfile.mkdtemp(prefix="canical-uml-"))
    rdir = rdir.resolve()
    rdir.mkdir(parents=True, exist_ok=True)
    for stale in ("status", "status.tmp", "setup_error", "ready", "stdout.txt", "stderr.txt",
                  "journal.txt"):
        (rdir / stale).unlink(missing_ok=True)
    workdir = Path(cwd if cwd is not None else os.getcwd()).resolve()
    guest_env = guest_environment(os.environ if env is None else env, rdir)
    if systemd:
        guest_env[ENV_IN_SYSTEMD] = "1"
        (rdir / GUEST_UNIT).write_text(_guest_unit(rdir))
    init_text, command_text = render_init_script(uml, rdir, command, workdir, guest_env, channels,
                                                 systemd=systemd)
    (rdir / "command.sh").write_text(command_text)
    init = rdir / "init.sh"
    init.write_text(init_text)
    init.chmod(0o755)

    host_env = {k: v for k, v in os.environ.items() if k not in {"TMPDIR", "TMP", "TEMP"}}
    if shim is not None:
        preload = host_env.get("LD_PRELOAD")
        host_env["LD_PRELOAD"] = f"{shim} {preload}" if preload else str(shim)
    umid = f"canical-{os.getpid()}-{rdir.name[-8:]}"
    argv = [str(uml.kernel), f"mem={mem or os.environ.get(ENV_MEM, '2G')}",
            "rootfstype=hostfs", "rootflags=/", "ro", "quiet", f"umid={umid}",
            f"uml_dir={rdir}", f"init={init}", "con=null", "con0=fd:0,fd:1"]

    start = time.monotonic()
    wall_start = time.time()
    timed_out = False
    with open(rdir / "console.log", "wb") as console, open(os.devnull, "rb") as devnull:
        proc = subprocess.Popen(argv, stdin=devnull, stdout=console, stderr=subprocess.STDOUT,
                                env=host_env, start_new_session=True)
        try:
            proc.wait(timeout=timeout)
        except subprocess.TimeoutExpired:
            timed_out = True
        except BaseException:  # KeyboardInterrupt: never leave a guest behind
            _kill_group(proc.pid)
            proc.wait()
            raise
        finally:
            # Also reaps helpers that outlive a kernel that halted or crashed.
            _kill_group(proc.pid)
        kernel_rc = proc.wait()
    duration = time.monotonic() - start

    status_text = _read(rdir / "status").strip()
    boot = None  # the init script touches "ready" once the vcans are up
    with contextlib.suppress(OSError):
        boot = max(0.0, (rdir / "ready").stat().st_mtime - wall_start)
    return GuestResult(
        returncode=int(status_text) if status_text.lstrip("-").isdigit() else None,
        stdout=_read(rdir / "stdout.txt"),
        stderr=_read(rdir / "stderr.txt"),
        journal=_read(rdir / "journal.txt"),
        console=_read(rdir / "console.log"),
        run_dir=rdir,
        duration=duration,
        boot_duration=boot,
        timed_out=timed_out,
        setup_error=_read(rdir / "setup_error").strip() or None,
        kernel_returncode=None if timed_out else kernel_rc,
    )


def run_script_on_vcan(timeout: float = 900.0) -> int | None:
    """For a script that needs vcan: where the host has none, run this same command in a guest.

    Returns the guest's exit status after relaying its output, or ``None`` when the
    caller is already where vcan is (host vcan, or inside the guest) and should run.
    """
    if os.environ.get(ENV_IN_UML) == "1" or host_vcan_status().usable:
        return None
    result = run_in_uml([sys.executable, *sys.argv], timeout=timeout)
    sys.stdout.write(result.stdout)
    if not result.ok:
        print(result.describe(), file=sys.stderr)
    return result.returncode if result.returncode is not None else 125


def _main(argv: Sequence[str]) -> int:
    """``python tests/support/vcan_harness.py CMD...``: run CMD in a guest, echo output, keep the run dir."""
    if not argv:
        status = host_vcan_status(create=False)
        print(f"host vcan: {status.reason}")
        print(f"uml: {uml_unavailable_reason() or 'available'}")
        return 0
    result = run_in_uml(argv)
    sys.stdout.write(result.stdout)
    sys.stderr.write(result.stderr)
    if not result.ok:
        print(result.describe(), file=sys.stderr)
    print(f"[guest {result.duration:.1f} s, run dir {result.run_dir}]", file=sys.stderr)
    return result.returncode if result.returncode is not None else 125


if __name__ == "__main__":
    sys.exit(_main(sys.argv[1:]))
