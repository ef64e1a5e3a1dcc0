"""Files from an installed package's own source distribution, for tests against published data.

Why downloaded and not copied: they are the package's files (cantools' test DBCs, allantools'
Stable32 tables), for the installed version. Fetched once from the package index (``pip
download``, the registry the set-up installs from) into a cache.
"""

from __future__ import annotations

import hashlib
import os
import subprocess
import sys
import tarfile
import tempfile
from pathlib import Path


def _cache_root() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "canical-tests"


def sdist_files(package: str, version: str, wanted: tuple[str, ...]) -> Path:
    """A folder of the sdist's files whose paths end in one of ``wanted`` (their paths inside
    the archive flattened, ``/`` as ``__``), fetched and unpacked on first use.

    RuntimeError when the source distribution cannot be had.
    """
    key = hashlib.sha256("\n".join(wanted).encode()).hexdigest()[:10]
    target = _cache_root() / f"{package}-{version}-{key}"
    if (target / "COMPLETE").is_file():
        return target
    with tempfile.TemporaryDirectory() as tmp:
        done = subprocess.run(
            [sys.executable, "-m", "pip", "download", "--quiet", "--no-deps", "--no-binary", ":all:",
             f"{package}=={version}", "-d", tmp],
            capture_output=True, text=True, check=False, timeout=300)
        archives = sorted(Path(tmp).glob(f"{package}-*.tar.gz"))
        if done.returncode != 0 or not archives:
            raise RuntimeError(f"cannot download {package} {version}'s source distribution: "
                               f"{done.stderr.strip()[-300:]}")
        target.mkdir(parents=True, exist_ok=True)
        with tarfile.open(archives[0]) as tar:
            for member in tar.getmembers():
                if member.isfile() and member.name.endswith(wanted):
                    data = tar.extractfile(member)
                    assert data is not None
                    (target / member.name.split("/", 1)[1].replace("/", "__")).write_bytes(data.read())
    (target / "COMPLETE").write_text("ok\n")
    return target
