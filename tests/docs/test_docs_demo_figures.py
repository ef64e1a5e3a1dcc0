"""The figures the documentation quotes from the demo are the demo's: a test runs its CSV half.

``docs/getting-started.md`` holds the demo's output between ``<!-- demo-output -->`` markers and
quotes figures from it in prose between ``<!-- demo-figures -->`` markers. Both are compared
with what ``canical demo --no-bus`` prints now (the default seed gives the same figures on every
run), so a change to the models or the simulator that moves a figure fails here until the page
says the new one. The bus half is not quoted by number.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from canical.commands.cli import main

PAGE = Path(__file__).resolve().parents[2] / "docs" / "getting-started.md"
#: A quoted figure: a decimal number, a ratio (8.8x) or a percentage (64%).
FIGURE = re.compile(r"(?<![\w.])[-+]?\d+(?:\.\d+)?(?:x|%)(?!\w)|(?<![\w.])[-+]?\d+\.\d+(?![\w.])")


def between(text: str, marker: str) -> str:
    match = re.search(rf"<!-- {marker}\b[^>]*-->(.*?)<!-- /{marker} -->", text, re.S)
    assert match, f"{PAGE.name}: no <!-- {marker} --> section"
    return match.group(1)


def transcript(text: str) -> list[str]:
    block = between(text, "demo-output").strip()
    assert block.startswith("```") and block.endswith("```"), "the demo's output is one fenced block"
    return [line.rstrip() for line in block.strip("`").strip("\n").splitlines()]


def quoted_figures(text: str) -> list[str]:
    return FIGURE.findall(between(text, "demo-figures"))


@pytest.fixture(scope="module")
def demo_output(tmp_path_factory) -> list[str]:
    import contextlib
    import io

    out = tmp_path_factory.mktemp("demo") / "canical-demo"
    buffer = io.StringIO()
    with contextlib.redirect_stdout(buffer):
        assert main(["demo", "--no-bus", "--out", str(out)]) == 0
    return [line.rstrip() for line in buffer.getvalue().replace(str(out), "canical-demo").splitlines()]


def test_the_page_shows_what_the_demo_prints(demo_output):
    shown = transcript(PAGE.read_text(encoding="utf-8"))
    assert shown == demo_output[: len(shown)] and len(shown) == len(demo_output), (
        "docs/getting-started.md shows other demo output than `canical demo --no-bus` prints now:\n"
        + "\n".join(demo_output)
    )


def test_every_figure_quoted_in_prose_is_printed_by_the_demo(demo_output):
    printed = set(FIGURE.findall("\n".join(demo_output)))
    quoted = quoted_figures(PAGE.read_text(encoding="utf-8"))
    assert len(quoted) >= 8, quoted
    missing = [f for f in quoted if f not in printed]
    assert not missing, f"docs/getting-started.md quotes {missing}, which the demo does not print"
