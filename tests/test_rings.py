"""The package's rings: every import of every canical module runs downward, never up.

The rule is read from the import graph (all imports, including those inside functions and
under TYPE_CHECKING), so it stays true as code is added: a module may import its own
package and anything in a lower ring, never a sibling of its ring or anything above.
"""

from __future__ import annotations

import ast
import collections
import functools
from pathlib import Path

import pytest
from support.import_graph import PACKAGE, RANK, module_name, unit_of, violations


def test_every_import_runs_downward() -> None:
    assert violations() == []


def test_every_module_is_in_a_ring() -> None:
    units = {unit_of(module_name(p)) for p in PACKAGE.rglob("*.py")} - {""}
    assert sorted(units - set(RANK)) == []


@pytest.mark.parametrize("package", [n for n in RANK if (PACKAGE / n).is_dir()])
def test_each_ring_package_says_what_it_is_for(package: str) -> None:
    doc = ast.get_docstring(ast.parse((PACKAGE / package / "__init__.py").read_text()))
    assert doc and len(doc.split()) >= 20, f"canical/{package}/__init__.py needs a docstring"


def test_the_checker_sees_an_upward_import(tmp_path: Path) -> None:
    """A models/ module importing calibrate/ is caught (the rule is not vacuous)."""
    fake = tmp_path / "canical"
    (fake / "models").mkdir(parents=True)
    (fake / "calibrate").mkdir()
    (fake / "models" / "bad.py").write_text("def f():\n    from canical.calibrate import plateaus\n")
    (fake / "calibrate" / "ok.py").write_text("from canical.models import piecewise\n")
    assert violations(fake) == ["canical/models/bad.py:2: models imports canical.calibrate (a ring above)"]


@functools.cache
def outside_imports() -> dict[str, set[str]]:
    """Per package: what canical's other rings and the tests import from ``canical.<package>``
    (its submodules, and names taken from the package itself)."""
    found: dict[str, set[str]] = collections.defaultdict(set)
    for path in [*PACKAGE.rglob("*.py"), *Path(__file__).resolve().parent.rglob("*.py")]:
        home = unit_of(module_name(path)) if path.is_relative_to(PACKAGE) else ""
        for node in ast.walk(ast.parse(path.read_text(), str(path))):
            if isinstance(node, ast.ImportFrom) and node.level == 0 and node.module:
                parts = node.module.split(".")
                if parts[0] == "canical" and len(parts) > 1 and parts[1] != home:
                    found[parts[1]] |= {parts[2]} if len(parts) > 2 else {a.name for a in node.names}
            elif isinstance(node, ast.Import):
                for a in node.names:
                    parts = a.name.split(".")
                    if parts[0] == "canical" and len(parts) > 2 and parts[1] != home:
                        found[parts[1]].add(parts[2])
    return found


def declared_all(package: str) -> list[str] | None:
    """The package's ``__all__`` as written (None without one)."""
    for node in ast.parse((PACKAGE / package / "__init__.py").read_text()).body:
        if isinstance(node, ast.Assign) and any(getattr(t, "id", None) == "__all__" for t in node.targets):
            return [ast.literal_eval(e) for e in node.value.elts]  # type: ignore[attr-defined]
    return None


@pytest.mark.parametrize("package", [n for n in RANK if (PACKAGE / n).is_dir()])
def test_all_is_the_public_face_other_rings_use(package: str) -> None:
    """A package's ``__all__`` names exactly what other rings and the tests import from it, so a
    reader sees the package's face at its top, and a new outside use (or a dropped one) shows."""
    declared = declared_all(package)
    if declared is None:
        pytest.skip(f"canical/{package} declares no __all__")
    assert sorted(declared) == sorted(outside_imports()[package])
