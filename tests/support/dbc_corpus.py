"""A corpus of real DBC files for the codec tests: the ~90 test DBCs cantools' source
distribution ships (vehicles', vendors' and its own edge cases), for the installed version.

Why downloaded and not copied: they are cantools' files, and the version the compiled codec is
compared against is the installed one. Fetched once from the package index (``pip download``,
the same registry the set-up installs from) into a cache; ``CANICAL_DBC_CORPUS`` names a folder
of DBC files to use instead.
"""

from __future__ import annotations

import os
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path

import cantools


def _cache_root() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "canical-tests"


def corpus_dir() -> Path:
    """The folder of DBC files, fetched and unpacked on first use (RuntimeError: cannot be had)."""
    given = os.environ.get("CANICAL_DBC_CORPUS")
    if given:
        return Path(given)
    target = _cache_root() / f"cantools-{cantools.__version__}-dbc"
    if (target / "COMPLETE").is_file():
        return target
    with tempfile.TemporaryDirectory() as tmp:
        done = subprocess.run(
            [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--no-binary", ":all:",
             f"cantools=={cantools.__version__}", "-d", tmp],
            capture_output=True, text=True, check=False, timeout=300)
        archives = sorted(Path(tmp).glob("cantools-*.tar.gz"))
        if done.returncode != 0 or not archives:
            raise RuntimeError(f"cannot download cantools {cantools.__version__}'s source distribution "
                               f"for its DBC corpus: {done.stderr.strip()[-300:]}")
        target.mkdir(parents=True, exist_ok=True)
        with tarfile.open(archives[0]) as tar:
            for member in tar.getmembers():
                if member.isfile() and member.name.endswith(".dbc"):
                    data = tar.extractfile(member)
                    assert data is not None
                    flat = member.name.split("/", 1)[1].replace("/", "__")
                    (target / flat).write_bytes(data.read())
    (target / "COMPLETE").write_text("ok\n")
    return target


def corpus_files() -> list[Path]:
    return sorted(corpus_dir().glob("*.dbc"))
