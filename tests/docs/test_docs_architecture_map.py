"""The map of the rings in docs/architecture.md names every module of the package, so a module
added without a place on the map fails here instead of leaving the page behind the code."""

from __future__ import annotations

import re
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "canical"


def map_text() -> str:
    page = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    return page.split("```", 2)[1]  # the first fenced block is the map


def test_every_module_is_on_the_map() -> None:
    names = set(re.findall(r"[A-Za-z_]+", map_text()))
    modules = {p.stem for p in PACKAGE.rglob("*.py")
               if p.stem not in {"__init__", "__main__"} and p.parent.name != "commands"}
    assert sorted(modules - names) == []
