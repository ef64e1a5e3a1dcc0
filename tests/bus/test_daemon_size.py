"""The daemon stays a module a reader can hold: at most 450 lines, no class over 300 (issue 31).

Its parts live in modules of their own (links, the frame path's state, the reference handler,
the classification of frames); this fails when the loop starts gathering them again.
"""

from __future__ import annotations

import ast
from pathlib import Path

import canical.bus.daemon

MAX_LINES, MAX_CLASS_LINES = 450, 300


def test_daemon_module_and_its_classes_are_short() -> None:
    path = Path(canical.bus.daemon.__file__)
    text = path.read_text()
    assert len(text.splitlines()) <= MAX_LINES
    classes = [n for n in ast.walk(ast.parse(text)) if isinstance(n, ast.ClassDef)]
    assert classes, "no class found: the measure would pass for nothing"
    sizes = {c.name: (c.end_lineno or c.lineno) - c.lineno + 1 for c in classes}
    assert max(sizes.values()) <= MAX_CLASS_LINES, sizes


def test_the_measure_counts_a_class_from_its_first_to_its_last_line() -> None:
    """The measure itself: a class of 301 lines is over the limit."""
    body = "\n".join(f"    x{i} = {i}" for i in range(300))
    (cls,) = ast.parse(f"class Big:\n{body}\n").body
    assert isinstance(cls, ast.ClassDef) and (cls.end_lineno or 0) - cls.lineno + 1 == 301
