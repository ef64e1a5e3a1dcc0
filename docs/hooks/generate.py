"""MkDocs hook: the pages and figures made from the code, added to the site at build time.

Nothing here is written into ``docs/``: the reference pages (``docs/scripts/reference.py``) and
the science figures (``docs/scripts/figures.py``) exist only in the built site, so they cannot
be committed stale. A generator that fails (a configuration key the docs do not list, a figure
script that raises) fails the build.
"""

from __future__ import annotations

import logging
import sys
import time
from pathlib import Path

from mkdocs.structure.files import File, Files

SCRIPTS = Path(__file__).resolve().parents[1] / "scripts"
log = logging.getLogger("mkdocs.hooks.generate")


def on_files(files: Files, config) -> Files:
    if str(SCRIPTS) not in sys.path:
        sys.path.insert(0, str(SCRIPTS))
    import figures
    import reference

    started = time.perf_counter()
    for rel, text in reference.pages().items():
        files.append(File.generated(config, rel, content=text))
    for rel, png in figures.figures().items():
        files.append(File.generated(config, rel, content=png))
    log.info("generated the reference pages and figures in %.1f s", time.perf_counter() - started)
    return files
