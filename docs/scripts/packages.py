"""The package page: canical's rings, each package's modules and what each imports.

Why generated: the hand-drawn ring diagram in ``architecture.md`` drifted (a module it said was
pure wrote files, a package was missing). This page is drawn at build time from the ring table
and the import graph that ``tests/test_rings.py`` holds the code to (``tests/support/import_graph.py``),
and from each module's own docstring.
"""

from __future__ import annotations

import ast
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT / "tests") not in sys.path:
    sys.path.insert(0, str(ROOT / "tests"))

from support.import_graph import PACKAGE, RINGS, unit_imports  # noqa: E402

NOTE = ('!!! note "Generated"\n    This page is generated from the package\'s import graph, the ring '
        "table in `tests/support/import_graph.py` and each module's docstring when the documentation "
        "is built.\n")


def summary(path: Path) -> str:
    """A module's docstring, first sentence (its first line when that is all there is)."""
    doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8"))) or ""
    first = " ".join(doc.split("\n\n")[0].split())
    return first.replace("|", "\\|") or "—"


def unit_path(unit: str) -> Path:
    return PACKAGE / unit if (PACKAGE / unit).is_dir() else PACKAGE / f"{unit}.py"


def unit_rows(unit: str) -> list[str]:
    """One table row per module of a ring member (a root module is its own one row)."""
    path = unit_path(unit)
    if path.is_file():
        return [f"| `{unit}.py` | {summary(path)} |"]
    modules = sorted(p for p in path.glob("*.py") if p.name != "__init__.py")
    return [f"| `{unit}/{p.name}` | {summary(p)} |" for p in modules]


def ring_section(level: int, units: tuple[str, ...], imports: dict[str, set[str]]) -> list[str]:
    lines = [f"## Ring {level}: {', '.join(f'`{u}`' for u in units)}", ""]
    for unit in units:
        path = unit_path(unit)
        uses = ", ".join(f"`{u}`" for u in sorted(imports.get(unit, ()))) or "nothing of canical"
        head = summary(path / "__init__.py") if path.is_dir() else ""
        lines += [f"**`{unit}`**{' — ' + head if head else ''} Imports: {uses}.", "",
                  "| module | what it is for |", "|---|---|", *unit_rows(unit), ""]
    return lines


def page() -> str:
    imports = unit_imports()
    lines = ["# The package, ring by ring", "", NOTE,
             "Each ring imports only the rings below it, never a ring beside it on the same level "
             "(`tests/test_rings.py`). Top to bottom:", ""]
    for level in range(len(RINGS) - 1, -1, -1):
        lines += ring_section(level, RINGS[level], imports)
    return "\n".join(lines)
