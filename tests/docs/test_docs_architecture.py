"""docs/architecture.md and the generated package page stay true to the package.

The ring map is drawn from the code (``docs/scripts/packages.py``), so it lists every module by
construction; what is left to drift is the prose, so every package or module it names in
backticks must exist.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
PACKAGE = ROOT / "canical"
sys.path.insert(0, str(ROOT / "docs" / "scripts"))

import packages  # noqa: E402


def test_the_package_page_lists_every_module_under_its_ring() -> None:
    page = packages.page()
    for path in PACKAGE.rglob("*.py"):
        if path.name == "__init__.py":
            continue
        rel = path.relative_to(PACKAGE).as_posix()
        assert f"| `{rel}` |" in page, rel


def test_the_package_page_says_what_each_package_imports() -> None:
    page = packages.page()
    assert "**`sets`** — " in page
    sets_line = next(line for line in page.splitlines() if line.startswith("**`sets`**"))
    assert "`models`" in sets_line and "`bus`" not in sets_line


def named_paths(text: str) -> set[str]:
    """Backticked names that look like canical's packages or modules: `sets/`, `bus/daemon`."""
    return {m for m in re.findall(r"`([a-z_]+/(?:[a-z_]+)?)`", text)}


def test_every_package_and_module_the_prose_names_exists() -> None:
    text = (ROOT / "docs" / "architecture.md").read_text(encoding="utf-8")
    top_level = {"canical/", "firmware/", "dbc/", "services/", "systemd/", "docs/", "tests/",
                 "tests/docs/", "tests/support/", "tests/benchmarks/"}
    missing = []
    for name in named_paths(text) - top_level:
        package, _, module = name.partition("/")
        path = PACKAGE / package / (f"{module}.py" if module else "")
        if not path.exists():
            missing.append(name)
    assert missing == []
    assert named_paths("`sets/` and `bus/daemon`") == {"sets/", "bus/daemon"}
