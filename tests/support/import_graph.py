"""canical's rings and its import graph, read from the source with :mod:`ast`.

One place for both: ``tests/test_rings.py`` holds the code to the rings, and
``docs/scripts/packages.py`` draws the rings and each package's modules for the documentation
from the same table and the same graph, so the page cannot drift from the code.
"""

from __future__ import annotations

import ast
from dataclasses import dataclass
from pathlib import Path

PACKAGE = Path(__file__).resolve().parents[2] / "canical"

#: Bottom to top. A name is a package (``models``) or a module at the package root.
RINGS: tuple[tuple[str, ...], ...] = (
    ("errors", "progress", "bus_outage"),
    ("files",),
    ("models", "frames"),
    ("calibrate", "sessions", "tracking"),
    ("sets", "fieldlog"),
    ("closed_loop", "sim"),
    ("calibration",),
    ("report",),
    ("device", "fleet"),
    ("bus",),
    ("commands",),
    ("__main__",),
)
RANK = {name: level for level, names in enumerate(RINGS) for name in names}


@dataclass(frozen=True)
class Import:
    """One canical import of one module: where it is written and what it names."""

    line: int
    target: str  # dotted, relative imports resolved


def unit_of(module: str) -> str:
    """The ring member a dotted module belongs to: its first component below ``canical``."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""  # "" = the root package (__version__)


def module_name(path: Path, package: Path = PACKAGE) -> str:
    rel = path.relative_to(package.parent).with_suffix("")
    parts = rel.parts[:-1] if rel.name == "__init__" else rel.parts
    return ".".join(parts)


def imports_of(path: Path, package_dir: Path = PACKAGE) -> list[Import]:
    """Every canical import in the file (inside functions and TYPE_CHECKING too)."""
    this = module_name(path, package_dir)
    package = this if path.name == "__init__.py" else this.rpartition(".")[0]
    found: list[Import] = []
    for node in ast.walk(ast.parse(path.read_text(), str(path))):
        if isinstance(node, ast.Import):
            found += [Import(node.lineno, a.name) for a in node.names]
        elif isinstance(node, ast.ImportFrom):
            base = node.module or ""
            if node.level:
                anchor = package.split(".")[: len(package.split(".")) - node.level + 1]
                base = ".".join([*anchor, *([base] if base else [])])
            # "from canical import x": x may be a module of the root ring
            found += [Import(node.lineno, f"{base}.{a.name}" if base == "canical" else base)
                      for a in node.names]
    return [i for i in found if i.target == "canical" or i.target.startswith("canical.")]


def unit_imports(package_dir: Path = PACKAGE) -> dict[str, set[str]]:
    """Per ring member: the other ring members its modules import."""
    out: dict[str, set[str]] = {}
    for path in sorted(package_dir.rglob("*.py")):
        src = unit_of(module_name(path, package_dir))
        for imp in imports_of(path, package_dir):
            dst = unit_of(imp.target)
            if src and dst not in ("", src, "__version__"):
                out.setdefault(src, set()).add(dst)
    return out


def violations(package_dir: Path = PACKAGE) -> list[str]:
    """Every import that does not run downward, as ``file:line: what``."""
    out = []
    for path in sorted(package_dir.rglob("*.py")):
        src = unit_of(module_name(path, package_dir))
        where = path.relative_to(package_dir.parent)
        for imp in imports_of(path, package_dir):
            dst = unit_of(imp.target)
            if dst in ("", src) or dst == "__version__":
                continue
            if src not in RANK or dst not in RANK:
                out.append(f"{where}:{imp.line}: {src or 'canical'} or {dst} is in no ring (add it to RINGS)")
            elif RANK[dst] >= RANK[src]:
                out.append(f"{where}:{imp.line}: {src} imports {imp.target} "
                           f"({'a sibling' if RANK[dst] == RANK[src] else 'a ring above'})")
    return out
