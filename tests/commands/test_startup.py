"""``--help`` and argument errors answer at once: no numerical or CAN library is imported for them.

Checked through ``sys.modules`` in a fresh interpreter rather than by timing, which depends on
the machine's load; the figure (under 0.3 s) is measured with ``python -X importtime``.
"""

import json
import subprocess
import sys

import pytest

from canical.commands import COMMANDS

HEAVY = ("numpy", "scipy", "matplotlib", "can", "canopen", "cantools", "yaml")

PROBE = """
import json, sys
from canical.commands.cli import main
try:
    main(sys.argv[1:])
except SystemExit as exc:
    status = exc.code
else:
    status = None
heavy = sorted(m for m in sys.modules if m.split(".")[0] in {heavy})
print(json.dumps({{"status": status, "heavy": heavy}}))
"""


def probe(argv: list[str]) -> dict:
    run = subprocess.run([sys.executable, "-c", PROBE.format(heavy=set(HEAVY)), *argv],
                         capture_output=True, text=True, timeout=120)
    assert run.returncode == 0, run.stderr
    return json.loads(run.stdout.splitlines()[-1])


@pytest.mark.parametrize("argv", [["--help"], ["--version"], ["no-such-verb"]])
def test_top_level(argv):
    result = probe(argv)
    assert result["status"] in (0, 2)
    assert result["heavy"] == []


@pytest.mark.parametrize("verb", list(COMMANDS))
def test_help_of_every_verb_imports_nothing_heavy(verb):
    result = probe([verb, "--help"])
    assert result["status"] == 0
    assert result["heavy"] == []


@pytest.mark.parametrize("verb", list(COMMANDS))
def test_argument_errors_of_every_verb_import_nothing_heavy(verb):
    result = probe([verb, "--no-such-option"])
    assert result["status"] == 2
    assert result["heavy"] == []


def test_the_probe_sees_heavy_imports(tmp_path):
    """The check can fail: a verb that runs imports what it needs."""
    result = probe(["calibrate", str(tmp_path / "missing.csv"), "-o", str(tmp_path / "c.yaml")])
    assert result["status"] is None  # main returned (status 2, file not found) without SystemExit
    assert "numpy" in result["heavy"]
