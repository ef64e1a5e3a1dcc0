"""The progress line: its unit, and one final line however often the end is reported."""

from __future__ import annotations

import io

from canical.progress import Progress


def test_unit_and_one_final_line(monkeypatch):
    monkeypatch.setenv("CANICAL_PROGRESS", "1")
    out = io.StringIO()
    progress = Progress("apply", 16, stream=out, unit="MB")
    progress.update(4)
    progress.update(16)
    progress.update(16)
    assert out.getvalue() == "\rapply: 4/16 MB (25%)\rapply: 16/16 MB (100%)\n"


def test_silent_unless_asked(monkeypatch):
    monkeypatch.delenv("CANICAL_PROGRESS", raising=False)
    out = io.StringIO()
    Progress("apply", 2, stream=out).update(2)
    assert out.getvalue() == ""
