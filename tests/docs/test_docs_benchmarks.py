"""The benchmarks page shows only figures the scripts printed, as the scripts are now.

Why: the page used to quote figures by hand, and they went stale with the code. Now it includes,
per script, the output ``tests/benchmarks/record_figures.py`` recorded, with a digest of the
script's source: a script changed since its figures were recorded fails here, as does a script
without figures, a recorded file the page does not include, or a figure typed into the page.
"""

from __future__ import annotations

import re
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "benchmarks.md"
sys.path.insert(0, str(ROOT / "tests" / "benchmarks"))

import record_figures  # noqa: E402

SCRIPTS = sorted((ROOT / "tests" / "benchmarks").glob("bench_*.py"))
INCLUDE = re.compile(r'^--8<-- "benchmarks/([\w.-]+)"$', re.M)
#: A measured figure: a number in a unit only results come in (a time per frame, a size, a
#: ratio, a rate of frames, an rms error); the inputs the prose describes (rates, durations,
#: coupling in %) are not results.
FIGURE = re.compile(r"\b\d[\d,.]*\s*(?:µs|ns|ms|MB|KB|GB|×|x\b|frames/s)|\d\s*deg/s rms|\brms\s+\d")


def test_every_script_is_on_the_page() -> None:
    included = INCLUDE.findall(PAGE.read_text(encoding="utf-8"))
    assert sorted(included) == sorted(f"{s.stem}.md" for s in SCRIPTS), (
        "docs/benchmarks.md must include each script's recorded figures exactly once")


@pytest.mark.parametrize("script", SCRIPTS, ids=lambda p: p.stem)
def test_figures_were_printed_by_the_script_as_it_is(script: Path) -> None:
    figures = record_figures.figures_path(script.stem)
    redo = f"record them: python tests/benchmarks/record_figures.py {script.stem}"
    assert figures.is_file(), f"{script.name} has no recorded figures; {redo}"
    assert record_figures.recorded_digest(figures) == record_figures.script_digest(script), (
        f"{script.name} changed since its figures were recorded; {redo}")
    text = figures.read_text(encoding="utf-8")
    assert f"`python tests/benchmarks/{script.name}" in text, "the command that printed them is named"


def test_no_recorded_figures_without_a_script() -> None:
    recorded = sorted(p.stem for p in record_figures.FIGURES.glob("*.md"))
    assert recorded == sorted(s.stem for s in SCRIPTS)


def test_the_page_types_no_figure_itself() -> None:
    prose = [line for line in PAGE.read_text(encoding="utf-8").splitlines() if not INCLUDE.match(line)]
    typed = [line for line in prose if FIGURE.search(line)]
    assert not typed, f"figures typed into docs/benchmarks.md (record them instead): {typed}"


def test_output_becomes_tables_and_text_blocks() -> None:
    out = record_figures.as_markdown("title line\n  a   1.0\n\n| a | b |\n|---|---|\n| 1 | 2 |\nafter\n")
    table = "| a | b |\n|---|---|\n| 1 | 2 |"
    assert out == f"```text\ntitle line\n  a   1.0\n```\n\n{table}\n\n```text\nafter\n```"
