"""The ``canical`` command line: one module per command under :mod:`canical.commands`.

A :class:`~canical.errors.CanicalError` (bad input the user can fix) is printed
as one line on stderr with exit status 2; anything else is a bug and keeps its
traceback.
"""

from __future__ import annotations

import argparse
import importlib
import os
import sys
from collections.abc import MutableMapping, Sequence

from canical import __version__
from canical.commands import COMMANDS
from canical.errors import CanicalError


def build_parser(command: str | None = None) -> argparse.ArgumentParser:
    """The parser, with the full sub-parser of ``command`` only (``None``: all of them)."""
    parser = argparse.ArgumentParser(
        prog="canical",
        description="Scale-factor calibration of MEMS gyroscopes on the CAN bus.",
    )
    parser.add_argument("--version", action="version", version=f"canical {__version__}")
    sub = parser.add_subparsers(dest="command", metavar="COMMAND", required=True)
    for name, help_text in COMMANDS.items():
        if command is None or name == command:
            importlib.import_module(f"canical.commands.{name.replace('-', '_')}").register(sub)
        else:
            sub.add_parser(name, help=help_text)
    return parser


def skip_mdf4_import(argv: Sequence[str]) -> None:
    """Keep python-can from importing asammdf when no argument names an MDF4 (.mf4) file.

    python-can imports its optional MDF4 support (asammdf, which pulls in pandas and sympy)
    at ``import can`` whenever it is installed: 2.7 s on every start of the daemon, ``push``
    or ``record`` once ``canical[mf4]`` is installed. Only in a fresh process (``can`` not
    imported yet), and only for asammdf: python-can then treats MDF4 as not installed.
    """
    if "can" in sys.modules or "asammdf" in sys.modules:
        return
    if not any(a.lower().endswith((".mf4", ".mf4.gz")) for a in argv):
        sys.modules["asammdf"] = None  # type: ignore[assignment]  # import asammdf -> ImportError


#: The variables the BLAS libraries numpy may be built with read their thread count from.
BLAS_THREAD_VARIABLES = ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS")


def one_blas_thread(environ: MutableMapping[str, str]) -> None:
    """BLAS on one thread unless the user's environment says otherwise.

    Why: canical's linear algebra is many small products and least squares (the closed loop's
    fits, the Allan sums' dot products), where a BLAS thread pool spends more on waking its
    threads than it saves: ``canical noise`` on a 3 M-row record took 1.92 s with OpenBLAS's
    default threads and 0.69 s on one (2 cores). Only a fresh process: numpy not loaded yet.
    """
    if "numpy" in sys.modules:
        return
    for name in BLAS_THREAD_VARIABLES:
        environ.setdefault(name, "1")


def no_hugepage_advice(environ: MutableMapping[str, str]) -> None:
    """numpy's large arrays without its transparent-huge-page advice, unless the user's
    environment says otherwise (``NUMPY_MADVISE_HUGEPAGE``).

    Why: where the kernel compacts memory on a fault in advised ranges (``defrag`` set to
    ``madvise``, Debian's default), each fresh 2 MB page of a column being filled may wait for
    compaction; canical writes its long columns once, in order, and reads them a few times, so
    huge pages gain little: ``canical noise`` on an 18 M-row record took 4.1 s advised, 3.6 s
    not (2 cores, 24 GiB). Only a fresh process: numpy reads the variable when it is loaded.
    """
    if "numpy" not in sys.modules:
        environ.setdefault("NUMPY_MADVISE_HUGEPAGE", "0")


def main(argv: Sequence[str] | None = None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    one_blas_thread(os.environ)
    no_hugepage_advice(os.environ)
    skip_mdf4_import(argv)
    command = next((a for a in argv if not a.startswith("-")), "")
    parser = build_parser(command if command in COMMANDS else "")
    args = parser.parse_args(argv)
    try:
        return int(args.run(args) or 0)
    except CanicalError as exc:
        print(f"canical {args.command}: error: {exc}", file=sys.stderr)
        return exc.exit_status
    except KeyboardInterrupt:
        print(f"canical {args.command}: interrupted", file=sys.stderr)
        return 130
