"""A corpus of real DBC files for the codec tests: the ~90 test DBCs cantools' source
distribution ships (vehicles', vendors' and its own edge cases), for the installed version
(:mod:`support.sdist_files`); ``CANICAL_DBC_CORPUS`` names a folder of DBC files to use instead.
"""

from __future__ import annotations

import os
from pathlib import Path

import cantools

from support.sdist_files import sdist_files


def corpus_dir() -> Path:
    """The folder of DBC files (RuntimeError: they cannot be had)."""
    given = os.environ.get("CANICAL_DBC_CORPUS")
    if given:
        return Path(given)
    return sdist_files("cantools", cantools.__version__, (".dbc",))


def corpus_files() -> list[Path]:
    return sorted(corpus_dir().glob("*.dbc"))
