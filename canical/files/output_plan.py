"""Every output of a command checked before any is written, and put in place together.

Why: a command that fails half-way must not leave some of its outputs behind (a new
coefficient set beside a missing report looks like a success), and an output that cannot be
written must be one line naming it, not a traceback after minutes of fitting. So a command
declares its outputs when it starts::

    with output_plan(args.output, args.report, dirs=[args.report_dir]):
        ...  # compute and write as usual

Each output is checked at once: its folder exists (a declared folder: its nearest existing
ancestor) and accepts a new file (a temporary is created and removed, which catches /proc,
read-only and permission problems), and the target is not a folder or a device. While the
plan is open, every atomic write (:mod:`canical.files.atomic_file`) in this thread to a declared
output goes to a temporary file beside its target instead (other files, such as scratch
files the command reads back, are written at once); when the block ends cleanly they are
all renamed into place (missing folders made first), and when it raises, every temporary is
removed and nothing is written. Any ``OSError`` on the way (a full disk) becomes one
:class:`~canical.errors.CanicalError` line ``cannot write PATH: REASON``.
"""

from __future__ import annotations

import contextlib
import os
import stat
import tempfile
from collections.abc import Iterable, Iterator
from contextvars import ContextVar, Token
from pathlib import Path
from typing import IO

from canical.errors import CanicalError

PathLike = str | os.PathLike[str]

_CURRENT: ContextVar[OutputPlan | None] = ContextVar("canical_output_plan", default=None)


def current() -> OutputPlan | None:
    """The plan open in this thread, if any (atomic writes consult it)."""
    return _CURRENT.get()


def cannot_write(path: PathLike, reason: str) -> CanicalError:
    return CanicalError(f"cannot write {path}: {reason}")


def _reason(exc: OSError) -> str:
    return exc.strerror or str(exc)


def _existing_ancestor(path: Path) -> Path:
    """The nearest ancestor of ``path`` that exists (the folder new files would go under)."""
    parent = path.parent
    while not parent.exists() and parent != parent.parent:
        parent = parent.parent
    return parent


def _probe(directory: Path, target: PathLike) -> None:
    """Create and remove a temporary file in ``directory``: the only sure test that it takes one."""
    if not directory.is_dir():
        raise cannot_write(target, f"{directory} is not a folder")
    try:
        fd, name = tempfile.mkstemp(prefix=".canical-probe.", dir=directory)
    except OSError as exc:
        raise cannot_write(target, f"cannot create a file in {directory} ({_reason(exc)})") from None
    os.close(fd)
    os.unlink(name)


def check_file(path: PathLike) -> None:
    """An output file can be written: its folder exists and takes files, it is no folder or device."""
    target = Path(path)
    if target.is_dir():
        raise cannot_write(path, "it is a folder")
    if target.exists() and not stat.S_ISREG(target.stat().st_mode):
        raise cannot_write(path, "it is not a regular file")
    parent = target.parent
    if not parent.exists():
        raise cannot_write(path, f"no folder {parent}")
    _probe(parent, path)


def check_dir(path: PathLike) -> None:
    """An output folder exists and takes files, or can be made under a folder that does."""
    target = Path(path)
    if target.exists():
        if not target.is_dir():
            raise cannot_write(path, "it exists and is not a folder")
        _probe(target, path)
        return
    _probe(_existing_ancestor(target), path)


def user_file_mode() -> int:
    """The mode a new file gets from ``open()`` under this process's umask (0o644 under 022).

    Why: :func:`tempfile.mkstemp` creates its file 0600 whatever the umask, so a set written with
    it into ``/etc/canical`` was unreadable by the service's dynamic user. Read from
    ``/proc/self/status`` where the kernel shows it; else set and restored at once.
    """
    try:
        with open("/proc/self/status", encoding="ascii") as status:
            for line in status:
                if line.startswith("Umask:"):
                    return 0o666 & ~int(line.split()[1], 8)
    except (OSError, ValueError):
        pass
    mask = os.umask(0o022)
    os.umask(mask)
    return 0o666 & ~mask


class OutputPlan:
    """The outputs of one command run: checked up front, staged while it runs, moved in at the end."""

    def __init__(self, files: Iterable[PathLike | None] = (), dirs: Iterable[PathLike | None] = ()) -> None:
        self._dirs = [Path(d) for d in dirs if d is not None]
        self._files = [Path(f) for f in files if f is not None]
        for d in self._dirs:
            check_dir(d)
        for f in self._files:
            check_file(f)
        self._dirs = [d.resolve() for d in self._dirs]
        self._files = [f.resolve() for f in self._files]
        self._staged: dict[Path, Path] = {}  # target -> temporary beside it
        self._token: Token[OutputPlan | None] | None = None

    def __enter__(self) -> OutputPlan:
        self._token = _CURRENT.set(self)
        return self

    def __exit__(self, exc_type, exc, tb) -> None:
        assert self._token is not None, "__enter__ sets the token"
        _CURRENT.reset(self._token)
        if exc_type is None:
            self.commit()
        else:
            self.discard()

    def covers(self, path: PathLike) -> bool:
        """Whether ``path`` is one of the declared outputs (a file, or anything in a folder)."""
        target = Path(path).resolve()
        return target in self._files or any(target.is_relative_to(d) for d in self._dirs)

    def temp_path(self, path: PathLike) -> Path:
        """A temporary file that becomes ``path`` at commit, for writers that want a file name.

        Its name ends in the target's format suffix (``.asc``, or ``.asc.gz``) and has no other
        dot, since writers such as python-can's ``Logger`` choose the format from the suffixes.
        """
        target = Path(path)
        if target.is_dir():
            raise cannot_write(path, "it is a folder")
        where = target.parent if target.parent.exists() else _existing_ancestor(target)
        try:
            fd, name = tempfile.mkstemp(prefix=f".{target.stem.replace('.', '_')}-",
                                        suffix=_format_suffix(target), dir=where)
        except OSError as exc:
            raise cannot_write(path, _reason(exc)) from None
        os.fchmod(fd, user_file_mode())
        os.close(fd)
        previous = self._staged.pop(target, None)
        if previous is not None:
            previous.unlink(missing_ok=True)
        self._staged[target] = Path(name)
        return Path(name)

    @contextlib.contextmanager
    def open(self, path: PathLike, mode: str = "w") -> Iterator[IO]:
        """A handle on ``path``'s temporary, flushed to disk on clean exit."""
        tmp = self.temp_path(path)
        try:
            with open(tmp, mode, newline="" if "b" not in mode else None) as handle:
                yield handle
                handle.flush()
                os.fsync(handle.fileno())
        except OSError as exc:
            raise cannot_write(path, _reason(exc)) from None

    def commit(self) -> None:
        """Move every staged file into place (folders made first); on failure remove the rest."""
        target: Path  # each step that can fail names its target first
        try:
            for target in self._staged:
                target.parent.mkdir(parents=True, exist_ok=True)
            while self._staged:
                target, tmp = next(iter(self._staged.items()))
                os.replace(tmp, target)
                del self._staged[target]
        except OSError as exc:
            self.discard()
            raise cannot_write(target, _reason(exc)) from None

    def discard(self) -> None:
        """Remove every temporary: nothing of this run is written."""
        for tmp in self._staged.values():
            with contextlib.suppress(OSError):
                tmp.unlink()
        self._staged.clear()


def output_plan(*files: PathLike | None, dirs: Iterable[PathLike | None] = ()) -> OutputPlan:
    """Check a command's output files and folders now; use as ``with`` around the command's work."""
    return OutputPlan(files, dirs)


def _format_suffix(target: Path) -> str:
    """``.asc`` for ``x.asc``, ``.asc.gz`` for ``x.asc.gz``: what a suffix-dispatching writer reads."""
    if target.suffix.lower() == ".gz" and len(target.suffixes) >= 2:
        return "".join(target.suffixes[-2:])
    return target.suffix
