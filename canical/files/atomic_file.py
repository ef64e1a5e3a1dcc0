"""Write files so that a reader never sees half of one.

The content goes to a temporary file in the target's directory, is flushed to
disk, and is renamed over the target in one step. A crash or an error midway
leaves the old file (or none) in place, never a truncated one. The file gets the mode
``open()`` would give it under the user's umask (not :func:`tempfile.mkstemp`'s 0600).

While a command's :class:`~canical.files.output_plan.OutputPlan` is open, the rename
waits until the whole command has succeeded, together with its other outputs.
"""

from __future__ import annotations

import contextlib
import os
import tempfile
from collections.abc import Iterator
from pathlib import Path
from typing import IO

from canical.files import output_plan


@contextlib.contextmanager
def atomic_writer(path: str | os.PathLike[str], mode: str = "w") -> Iterator[IO]:
    """Yield a file handle whose content replaces ``path`` only on clean exit."""
    plan = output_plan.current()
    if plan is not None and plan.covers(path):
        with plan.open(path, mode) as handle:
            yield handle
        return
    target = Path(path)
    directory = target.parent if str(target.parent) else Path(".")
    fd, tmp_name = tempfile.mkstemp(prefix=f".{target.name}.", suffix=".tmp", dir=directory)
    try:
        os.fchmod(fd, output_plan.user_file_mode())  # as open() would make it, not mkstemp's 0600
        with os.fdopen(fd, mode, newline="" if "b" not in mode else None) as handle:
            yield handle
            handle.flush()
            os.fsync(handle.fileno())
        os.replace(tmp_name, target)
    except BaseException:
        with contextlib.suppress(FileNotFoundError):
            os.unlink(tmp_name)
        raise


def make_dirs(path: str | os.PathLike[str]) -> None:
    """Make a folder for outputs; under an output plan the folders come with the files, at the end."""
    plan = output_plan.current()
    if plan is None or not plan.covers(path):
        Path(path).mkdir(parents=True, exist_ok=True)


def write_text_atomic(path: str | os.PathLike[str], text: str) -> None:
    """Replace ``path`` with ``text`` atomically."""
    with atomic_writer(path, "w") as handle:
        handle.write(text)


def write_bytes_atomic(path: str | os.PathLike[str], data: bytes) -> None:
    """Replace ``path`` with ``data`` atomically."""
    with atomic_writer(path, "wb") as handle:
        handle.write(data)
