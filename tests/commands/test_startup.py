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


BLAS_PROBE = """
import json, os, sys
from canical.commands.cli import BLAS_THREAD_VARIABLES, main
try:
    main(["--version"])
except SystemExit:
    pass
import numpy  # loads its BLAS with the variables as main left them
print(json.dumps({name: os.environ.get(name) for name in BLAS_THREAD_VARIABLES}))
"""


@pytest.mark.parametrize("user", [None, "4"])
def test_blas_runs_on_one_thread_unless_the_user_says_otherwise(user):
    """Many small least squares and dot products: a BLAS thread pool costs more than it gives
    (``canical noise`` on a 3 M-row record: 1.92 s with OpenBLAS's own threads, 0.69 s on one)."""
    import os

    env = {k: v for k, v in os.environ.items() if k not in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS",
                                                            "MKL_NUM_THREADS")}
    if user is not None:
        env["OPENBLAS_NUM_THREADS"] = user
    run = subprocess.run([sys.executable, "-c", BLAS_PROBE], capture_output=True, text=True, timeout=120,
                         env=env)
    assert run.returncode == 0, run.stderr
    seen = json.loads(run.stdout.splitlines()[-1])
    assert seen["OPENBLAS_NUM_THREADS"] == (user or "1")
    assert seen["OMP_NUM_THREADS"] == seen["MKL_NUM_THREADS"] == "1"


HUGEPAGE_PROBE = """
import json
from canical.commands.cli import main
try:
    main(["--version"])
except SystemExit:
    pass
import numpy  # reads NUMPY_MADVISE_HUGEPAGE as main left it
print(json.dumps(bool(numpy._core.multiarray._get_madvise_hugepage())))
"""


@pytest.mark.parametrize("user", [None, "1"])
def test_numpy_gives_no_huge_page_advice_unless_the_user_says_otherwise(user):
    """Fresh 2 MB pages of a long column may each wait for the kernel's compaction where advised
    (``canical noise`` on an 18 M-row record: 4.1 s advised, 3.6 s not); numpy itself then
    reports the advice off, or on where the user's environment asks for it."""
    import os

    env = {k: v for k, v in os.environ.items() if k != "NUMPY_MADVISE_HUGEPAGE"}
    if user is not None:
        env["NUMPY_MADVISE_HUGEPAGE"] = user
    run = subprocess.run([sys.executable, "-c", HUGEPAGE_PROBE], capture_output=True, text=True,
                         timeout=120, env=env)
    assert run.returncode == 0, run.stderr
    assert json.loads(run.stdout.splitlines()[-1]) is (user == "1")
