"""CAN log formats by file name: which files are CAN logs and what they need to be read.

Kept apart from the log reader so that a command's ``--help`` and argument checks can
name the formats without importing python-can, numpy or cantools.
"""

from __future__ import annotations

import contextlib
import gzip
import importlib
import logging
import os
import sys
from collections.abc import Iterator
from pathlib import Path

from canical.errors import CanicalError

# The suffixes python-can's LogReader dispatches on (can.io.player.MESSAGE_READERS), each
# possibly followed by .gz. Listed, not looked up, so that --help needs no python-can import.
CANLOG_SUFFIXES = (".asc", ".blf", ".csv", ".db", ".log", ".mf4", ".trc")
CANLOG_FORMATS = ".log, .asc, .blf, .trc, .csv, .db, .mf4, each also .gz"
PYTHON_CAN_CSV_HEADER = "timestamp,arbitration_id,extended,remote,error,dlc,data"
DEFAULT_RAW_MESSAGE = "IMU_RAW"
DEFAULT_REF = "TABLE_REF.TableRate"
#: An axis whose raw signal comes in another message than the raw frame is held like an input,
#: under this prefix and the axis's name ("@x"): a name no input of a configuration can have.
HELD_AXIS_PREFIX = "@"


def log_format(path: str | os.PathLike[str]) -> str:
    """The format suffix of a log name, under any ``.gz``: ``x.asc.gz`` -> ``.asc``."""
    suffixes = [x.lower() for x in Path(path).suffixes]
    if suffixes and suffixes[-1] == ".gz":
        suffixes.pop()
    return suffixes[-1] if suffixes else ""


def is_canlog(path: str | os.PathLike[str]) -> bool:
    """Whether a file is a CAN log (anything else is read as a session CSV).

    By suffix, except ``.csv``: python-can's CSV log is told from a session CSV by its header.
    """
    fmt = log_format(path)
    if fmt not in CANLOG_SUFFIXES:
        return False
    return fmt != ".csv" or _first_line(path) == PYTHON_CAN_CSV_HEADER


def _first_line(path: str | os.PathLike[str]) -> str:
    opener = gzip.open if Path(path).suffix.lower() == ".gz" else open
    try:
        with opener(path, "rt", encoding="utf-8", errors="replace") as f:
            return f.readline().strip()
    except (OSError, EOFError):  # missing or unreadable: the session reader says what is wrong
        return ""


class HeldComplaints(logging.Handler):
    """python-can's log readers log each line they cannot parse, one warning per line (a CSV
    named ``.trc`` printed 2,463 of them). Held here instead, counted, the first one kept, so the
    reader can say it in one line (:meth:`check`)."""

    def __init__(self) -> None:
        super().__init__(logging.WARNING)
        self.count = 0
        self.first = ""

    def emit(self, record: logging.LogRecord) -> None:
        self.count += 1
        if not self.first:
            self.first = " ".join(record.getMessage().split())[:80]

    def check(self, name: str, frames: int) -> None:
        """No frame read and lines refused: not a log of its format (one error line); some
        frames and some lines refused: one warning line."""
        if not self.count:
            return
        fmt = log_format(name) or "a CAN log"
        what = f"{self.count} line(s) python-can could not read as {fmt} (first: {self.first})"
        if frames == 0:
            raise CanicalError(f"{name}: not a CAN log in its suffix's format: {what}")
        print(f"canical: warning: {name}: {what}; {frames} frames read", file=sys.stderr)


@contextlib.contextmanager
def held_complaints() -> Iterator[HeldComplaints]:
    """Hold python-can's per-line complaints while a log is read (see :class:`HeldComplaints`)."""
    logger = logging.getLogger("can.io")
    handler = HeldComplaints()
    propagate = logger.propagate
    logger.addHandler(handler)
    logger.propagate = False
    try:
        yield handler
    finally:
        logger.removeHandler(handler)
        logger.propagate = propagate


def require_log_support(path: str | os.PathLike[str]) -> None:
    """Fail in one line when the format needs an optional dependency that is not installed.

    python-can reads MDF4 with asammdf, an extra (``canical[mf4]``): it is large and only
    vehicle data loggers write MDF4, so a plain install does without it.
    """
    if log_format(path) != ".mf4":
        return
    try:
        importlib.import_module("asammdf")
    except ImportError:
        raise CanicalError(
            f"{path}: reading or writing MDF4 (.mf4) needs the optional dependency asammdf: "
            "pip install 'canical[mf4]'"
        ) from None
