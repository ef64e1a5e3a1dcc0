"""docs/own-imu.md, run as written: a J1939 and a CANopen IMU from their DBCs as shipped.

On the whole page, each YAML block whose first line is ``# NAME.yaml`` is written to that file,
and each ``$ canical ...`` line of a console block is run, in page order, in one folder holding
the two vendor DBCs (``tests/data``, the CANopen one also as ``vendor.dbc``); the lines a console block
shows after a command must be among what that command printed. A command that fails, or an
output line the command no longer prints, fails the test: the page cannot drift from the code.
"""

from __future__ import annotations

import re
import shlex
import shutil
from dataclasses import dataclass, field
from pathlib import Path

from canical.commands.cli import main

ROOT = Path(__file__).resolve().parents[2]
PAGE = ROOT / "docs" / "own-imu.md"
DBCS = ("vendor_j1939_gyro.dbc", "vendor_canopen_gyro.dbc")
START, END = "<!-- walkthrough: run by tests/docs/test_docs_own_imu.py -->", "<!-- end of walkthrough -->"
# Console blocks the test cannot run, by their title: what each needs (the vcan test runs it).
NOT_RUN = {'title="on the vehicle"': "a live bus: tests/docs/test_docs_own_imu_vcan.py"}


@dataclass
class Step:
    """A file the page writes, or a command it runs and the output lines it shows."""

    file: str | None = None
    text: str = ""
    argv: list[str] = field(default_factory=list)
    shown: list[str] = field(default_factory=list)


def walkthrough_steps(page: str, *, whole: bool = False) -> list[Step]:
    """The walkthrough's (or the whole page's) files and commands, in page order."""
    section = page if whole else page.split(START, 1)[1].split(END, 1)[0]
    steps: list[Step] = []
    for kind, title, body in re.findall(r"```(yaml|console)( [^\n]*)?\n(.*?)```", section, flags=re.S):
        if kind == "yaml":
            first, _, rest = body.partition("\n")
            if first.startswith("# ") and first.endswith(".yaml"):
                steps.append(Step(file=first[2:], text=rest))
            continue
        if title:
            assert title.strip() in NOT_RUN, f"console block titled {title.strip()}: not known to the test"
            continue
        for line in body.replace("\\\n", " ").splitlines():
            if line.startswith("$ "):
                argv = shlex.split(line[2:], comments=True)
                assert argv[0] == "canical", line
                steps.append(Step(argv=argv[1:]))
            elif line.strip():
                steps[-1].shown.append(line)
    return steps


def test_the_page_has_a_walkthrough_of_both_imus() -> None:
    steps = walkthrough_steps(PAGE.read_text(encoding="utf-8"))
    files = [s.file for s in steps if s.file]
    assert files == ["j1939-imu.yaml", "canopen-imu.yaml"]
    verbs = [s.argv[0] for s in steps if s.argv]
    assert verbs.count("calibrate") == 2 and verbs.count("apply") == 2 and verbs.count("serve") == 2


def test_the_whole_page_is_run_but_what_needs_a_live_bus() -> None:
    """Every command but serve on the vehicle's bus, which the vcan test runs; the tables' own
    files of §5 come from ``simulate --table-file``, on the page, not from the test."""
    page = PAGE.read_text(encoding="utf-8")
    steps = walkthrough_steps(page, whole=True)
    assert [s.file for s in steps if s.file] == ["vendor.yaml", "vendor-imu.yaml", "j1939-imu.yaml",
                                                 "canopen-imu.yaml"]
    run = sum(1 for s in steps if s.argv)
    written = len(re.findall(r"^\$ canical ", page, flags=re.M))
    not_run = sum(page.count(f"```console {title}") for title in NOT_RUN)
    assert run == 24 and written == run + 1 and not_run == 1, (run, written, not_run)
    assert (ROOT / NOT_RUN['title="on the vehicle"'].split(": ")[1]).is_file()
    assert [s.argv[1] for s in steps if "--table-file" in s.argv] == ["session", "triad"]
    assert any(s.argv.count("--reference") == 3 for s in steps)  # three axes from three logs


def test_every_command_of_the_walkthrough_runs_as_shown(tmp_path: Path, monkeypatch, capsys) -> None:
    for name in DBCS:
        shutil.copy(ROOT / "tests" / "data" / name, tmp_path / name)
    shutil.copy(ROOT / "tests" / "data" / DBCS[1], tmp_path / "vendor.dbc")
    monkeypatch.chdir(tmp_path)
    for step in walkthrough_steps(PAGE.read_text(encoding="utf-8"), whole=True):
        if step.file:
            (tmp_path / step.file).write_text(step.text, encoding="utf-8")
            continue
        capsys.readouterr()
        code = main(step.argv)
        out = capsys.readouterr()
        assert code == 0, f"canical {shlex.join(step.argv)}: exit {code}\n{out.err}"
        printed = out.out.splitlines()
        missing = [line for line in step.shown if line not in printed]
        assert not missing, f"canical {shlex.join(step.argv)} no longer prints {missing}:\n{out.out}"
