"""Every benchmark script still runs: each ``bench_*.py`` here, in its ``--quick`` mode.

Why: the benchmarks are scripts nobody runs until a figure is needed, so a change elsewhere
(a renamed attribute, a term kind added) broke them silently; ``bench_firmware_eval.py`` died
with ``KeyError: 'gated'`` for weeks. Parametrised over the scripts found in this directory, so
a new script is covered without editing this file; it must accept ``--quick`` (small sizes,
figures meaningless, nothing asserted about them). Scripts that need SocketCAN (they call
``vcan_harness.run_script_on_vcan``) run marked ``vcan``, so inside the vcan guest with the
other vcan tests; their argument parsing (``--help``) also runs on the host.
"""

from __future__ import annotations

import os
import subprocess
import sys
from pathlib import Path

import pytest

HERE = Path(__file__).resolve().parent
ROOT = HERE.parents[1]
SCRIPTS = sorted(HERE.glob("bench_*.py"))
QUICK_TIMEOUT_S = 600.0


def needs_vcan(script: Path) -> bool:
    return "run_script_on_vcan" in script.read_text()


def run(script: Path, *args: str) -> subprocess.CompletedProcess[str]:
    path = os.environ.get("PYTHONPATH")
    env = {**os.environ, "MPLBACKEND": "Agg",
           "PYTHONPATH": f"{ROOT}{os.pathsep}{path}" if path else str(ROOT)}
    return subprocess.run([sys.executable, str(script), *args], cwd=ROOT, env=env, capture_output=True,
                          text=True, timeout=QUICK_TIMEOUT_S, check=False)


def test_scripts_are_found() -> None:
    assert len(SCRIPTS) >= 12


@pytest.mark.parametrize("script", [s for s in SCRIPTS if needs_vcan(s)], ids=lambda p: p.stem)
def test_parses_its_arguments(script: Path) -> None:
    """A script that runs in the guest is at least imported and parses its arguments here."""
    result = run(script, "--help")
    assert result.returncode == 0, result.stderr[-4000:]
    assert "--quick" in result.stdout


QUICK = [pytest.param(s, id=s.stem, marks=[pytest.mark.vcan] if needs_vcan(s) else []) for s in SCRIPTS]


@pytest.mark.parametrize("script", QUICK)
def test_runs_in_quick_mode(script: Path) -> None:
    result = run(script, "--quick")
    tail = f"{result.stdout[-2000:]}\n{result.stderr[-4000:]}"
    assert result.returncode == 0, f"{script.name} --quick failed:\n{tail}"
    assert result.stdout.strip(), f"{script.name} --quick printed nothing"


def test_why_drift_runs_on_a_seed() -> None:
    """The evidence script behind the closed loop's drift rules (not a bench_*: no quick mode)."""
    result = run(Path(__file__).with_name("why_drift.py"), "--class", "drift", "--seeds", "1000")
    assert result.returncode == 0, result.stderr[-4000:]
    assert "judgements on 1 seeds" in result.stdout
    assert "a channel written into the set on" in result.stdout


def test_bench_blind_draws_a_fresh_blind_sample_from_another_root() -> None:
    """``--root``, as the benchmarks page gives it: one blind case of each class, scores only."""
    script = Path(__file__).with_name("bench_blind.py")
    result = run(script, "--quick", "--root", "44777576110303", "--blind", "1")
    assert result.returncode == 0, result.stderr[-4000:]
    for within in ("any case", "drift, no channel effect", "listed effect"):
        assert f"blind, {within}: right" in result.stdout
