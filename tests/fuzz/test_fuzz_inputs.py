"""Everything canical loads, mutated: one bounded line or a correct result, never a traceback.

Issue 34 found tracebacks, non-finite rates and implausible states applied in 1,050 mutated
inputs. This fuzzer runs every surface a vehicle or a lab loads through the real entry point
(``canical.commands.cli.main`` in-process, a few as a process) or the loader the daemon calls, with the CRC
recomputed after each mutation so it reaches the checks behind it:

* single-axis sets and IMU sets (``apply``, and ``serve --check`` for some IMU sets);
* daemon configurations (``serve --check``), a key given twice among them;
* learned-bias state files (the loader the daemon calls at start);
* table reference files (``calibrate --reference``'s reading and alignment).

For each: no exception but a refusal, a refusal is one line of bounded length, no numpy warning,
any CSV written is whole (every row, every column) with finite rates, no temporary file left and
no output on a refusal, any state loaded is within the tracker's limits. Seeded; about 500
mutations in well under a minute. ``CANICAL_FUZZ_SCALE=20`` for a long run,
``CANICAL_FUZZ_SEED`` for other draws (tests/support/mutations.py).
"""

from __future__ import annotations

import csv
import json
import math
import random
import re
import warnings
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml
from support.daemon_fixtures import ALL_TERMS, DBC, imu_set_config, write_config, write_imu_set, write_sets
from support.mutations import SEED, Mutant, count, duplicate_a_key, mutants
from support.table_clock import own_clock_case, table_csv

from canical.commands.cli import main
from canical.errors import MAX_MESSAGE_CHARS, CanicalError
from canical.sessions.reference_clock import align_reference, join_reference
from canical.sessions.table_file import read_table_trace
from canical.sets import coefficient_file
from canical.sets.finite_outputs import RATE_LIMIT_DPS
from canical.tracking import state_file
from canical.tracking.config import TrackerConfig
from canical.tracking.estimate import AxisBias

#: A refusal's line: "canical COMMAND: error: " and the bounded message.
MAX_LINE = MAX_MESSAGE_CHARS + 40
ROWS = 40


@dataclass
class Findings:
    """Defects found over one surface: what was done and what went wrong (shown when any)."""

    runs: int = 0
    defects: list[str] = field(default_factory=list)
    outcomes: Counter[str] = field(default_factory=Counter)

    def outcome(self, refusal: str | None) -> None:
        """Tally an accepted input or a refusal's reason (its words, without paths and numbers)."""
        text = re.sub(r"^(bias state )?\S+: ", "", (refusal or "accepted").split("error: ", 1)[-1])
        self.outcomes[" ".join(re.sub(r"[-+]?\d[\d.e+-]*|'[^']*'", "#", text).split())[:50]] += 1

    def add(self, mutant: Mutant, what: str) -> None:
        self.defects.append(f"{'; '.join(mutant.done)}: {what}"[:400])

    def check(self) -> None:
        """No defect; and the mutations reached the checks (some accepted, most not a CRC refusal)."""
        print(f"\n{self.runs} runs, {len(self.defects)} defects; outcomes:",
              dict(self.outcomes.most_common(12)))
        assert self.outcomes["accepted"] > 0 and len(self.outcomes) > 3, self.outcomes
        assert sum(n for k, n in self.outcomes.items() if "CRC" in k) < self.runs / 4, self.outcomes
        assert not self.defects, f"{len(self.defects)} of {self.runs}:\n" + "\n".join(self.defects[:15])


def dump_yaml(tree: Any) -> str:
    return yaml.safe_dump(tree, sort_keys=False, allow_unicode=True)


def seal_set(tree: Any) -> None:
    """The set's CRC recomputed over the mutated content (0 where the content has no JSON form)."""
    seal(tree, coefficient_file.content_crc)


def seal(tree: Any, crc: Callable[[Any], int]) -> None:
    """``crc32`` recomputed by ``crc`` over the rest of ``tree`` (0 where it has no JSON form)."""
    if isinstance(tree, dict):
        tree.pop("crc32", None)
        try:
            tree["crc32"] = f"0x{crc(tree):08x}"
        except (TypeError, ValueError, RecursionError):
            tree["crc32"] = "0x00000000"


def run_cli(argv: list[str], capsys: pytest.CaptureFixture[str]) -> tuple[int, str, str, list[str]]:
    """Exit status, stdout, stderr and numpy's warnings of one in-process run (exceptions pass)."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        try:
            code = main(argv)
        except SystemExit as exc:  # argparse: a usage error
            code = exc.code if isinstance(exc.code, int) else 2
    out = capsys.readouterr()
    return code, out.out, out.err, [str(w.message) for w in caught if issubclass(w.category, RuntimeWarning)]


def refusal_problem(err: str) -> str | None:
    lines = err.strip().splitlines()
    if len(lines) != 1:
        return f"refusal of {len(lines)} lines: {err[:200]!r}"
    if len(lines[0]) > MAX_LINE:
        return f"refusal of {len(lines[0])} characters"
    return None


def csv_problem(path: Path, rate_columns: tuple[str, ...]) -> str | None:
    """Why a written CSV is not whole and finite (None: it is)."""
    with open(path, newline="") as handle:
        rows = list(csv.reader(handle))
    header, body = rows[0], rows[1:]
    if len(body) != ROWS or any(len(r) != len(header) for r in body):
        return f"output not whole: {len(body)} rows"
    for name in rate_columns:
        values = [float(r[header.index(name)]) for r in body]
        if not all(math.isfinite(v) and abs(v) <= RATE_LIMIT_DPS * (1 + 1e-9) for v in values):
            beyond = [v for v in values if not abs(v) <= RATE_LIMIT_DPS]
            return f"{name} beyond the proven bound: {beyond[:3]}"
    return None


def apply_run(findings: Findings, mutant: Mutant, argv: list[str], out: Path, rate_columns: tuple[str, ...],
              capsys: pytest.CaptureFixture[str]) -> None:
    """One ``apply``: a refusal in one line and no output, or a whole, finite CSV; no temp files."""
    folder = out.parent
    before = {p.name for p in folder.iterdir()}
    findings.runs += 1
    try:
        code, _, err, warned = run_cli(argv, capsys)
    except Exception as exc:
        findings.add(mutant, f"traceback {type(exc).__name__}: {str(exc)[:150]}")
        return
    left = {p.name for p in folder.iterdir()} - before - {out.name}
    problem = (f"warnings {warned[:2]}" if warned else f"files left {sorted(left)}" if left
               else f"exit {code}" if code not in (0, 2) else None)
    findings.outcome(err if code == 2 else None)
    if problem is None and code == 2:
        problem = refusal_problem(err) or ("output written on a refusal" if out.exists() else None)
    elif problem is None:
        problem = csv_problem(out, rate_columns)
    if problem:
        findings.add(mutant, problem)
    out.unlink(missing_ok=True)


@pytest.fixture(scope="module")
def folder(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """Sets with every term kind, the IMU set of them, a drive through and beyond the span."""
    root = tmp_path_factory.mktemp("fuzz")
    write_sets(root, terms=ALL_TERMS)
    write_imu_set(root, terms=ALL_TERMS)
    imu_set_config(root, "imu")
    write_config(root, "can0")
    lo, hi = coefficient_file.load(root / "imu-x.yaml").span_raw
    rows = ["time_s,raw,raw_x,raw_y,raw_z,temp_c,supply_v"]
    for i in range(ROWS):
        r = lo + (hi - lo) * (1.4 * i / (ROWS - 1) - 0.2)
        rows.append(f"{i * 0.01:.2f},{r:.1f},{r:.1f},{-r:.1f},{r / 2:.1f},{20 + i / 10:.1f},"
                    f"{5 + i / 1000:.3f}")
    (root / "drive.csv").write_text("\n".join(rows) + "\n")
    return root


def work(root: Path, name: str) -> Path:
    path = root / name
    path.mkdir(exist_ok=True)
    return path


def test_single_axis_sets(folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    base = yaml.safe_load((folder / "imu-x.yaml").read_text())
    here, findings = work(folder, "single"), Findings()
    rng = random.Random(SEED)
    for mutant in mutants(base, count(100), SEED):
        seal_set(mutant.tree)
        path = here / "set.yaml"
        text = mutant.text(dump_yaml)
        if rng.random() < 0.1:
            text = duplicate_a_key(text, rng)
            mutant.done.append("a key given twice")
        path.write_text(text)
        out = here / "out.csv"
        apply_run(findings, mutant, ["apply", str(path), str(folder / "drive.csv"), "-o", str(out),
                                     "--raw-column", "raw"], out, ("rate_dps",), capsys)
    findings.check()


def test_imu_sets(folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``apply`` on every mutant; ``serve --check`` (the daemon's loading) on every fourth."""
    base = yaml.safe_load((folder / "imu-set.yaml").read_text())
    here, findings = work(folder, "imu"), Findings()
    config = yaml.safe_load((folder / "imu.yaml").read_text())
    config["imu_set"] = str(here / "imu-set.yaml")
    (here / "imu.yaml").write_text(dump_yaml(config))
    for i, mutant in enumerate(mutants(base, count(100), SEED + 1)):
        seal_set(mutant.tree)
        path = here / "imu-set.yaml"
        path.write_text(mutant.text(dump_yaml))
        out = here / "out.csv"
        apply_run(findings, mutant, ["apply", str(path), str(folder / "drive.csv"), "-o", str(out)], out,
                  ("rate_x_dps", "rate_y_dps", "rate_z_dps"), capsys)
        if i % 4 == 0:
            check_run(findings, mutant, ["serve", "--config", str(here / "imu.yaml"), "--check"], capsys)
    findings.check()


def check_run(findings: Findings, mutant: Mutant, argv: list[str],
              capsys: pytest.CaptureFixture[str]) -> None:
    """One command that writes nothing: exit 0, or 2 with one bounded line; no traceback."""
    findings.runs += 1
    try:
        code, _, err, warned = run_cli(argv, capsys)
    except Exception as exc:
        findings.add(mutant, f"traceback {type(exc).__name__}: {str(exc)[:150]}")
        return
    findings.outcome(err if code == 2 else None)
    problem = (f"warnings {warned[:2]}" if warned else f"exit {code}" if code not in (0, 2)
               else refusal_problem(err) if code == 2 else None)
    if problem:
        findings.add(mutant, problem)


def test_daemon_configurations(folder: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """``serve --check`` on mutated configurations (per-axis and IMU set), a key given twice in some."""
    findings, rng = Findings(), random.Random(SEED + 2)
    for name in ("can0", "imu"):
        base = yaml.safe_load((folder / f"{name}.yaml").read_text())
        for mutant in mutants(base, count(40), SEED + 2 + len(name)):
            text = mutant.text(dump_yaml)
            if rng.random() < 0.15:
                text = duplicate_a_key(text, rng)
                mutant.done.append("a key given twice")
            path = folder / "fuzz-config.yaml"
            path.write_text(text)
            check_run(findings, mutant, ["serve", "--config", str(path), "--check"], capsys)
    findings.check()


STATE_AXES = ("x", "y", "z")
STATE_SET_ID = 0x1234ABCD


def seal_state(tree: Any) -> None:
    """The state file's CRC recomputed as the daemon writes it."""
    seal(tree, state_file._crc)


def state_key_twice(text: str) -> str:
    """The first state's ``b0`` given twice, the CRC recomputed over what json keeps (the last)."""
    twice = text.replace('"b0": ', '"b0": 0.5, "b0": ', 1)
    try:
        content = json.loads(twice)
        crc = f"0x{state_file._crc({k: v for k, v in content.items() if k != 'crc32'}):08x}"
        return twice.replace(str(content["crc32"]), crc, 1)
    except (ValueError, TypeError, KeyError, RecursionError):
        return twice


def state_problem(loaded: state_file.LoadedState, limits: state_file.StateLimits) -> str | None:
    """Why what the loader gave is not fit to start a tracker from (None: it is)."""
    if "\n" in loaded.note or len(loaded.note) > MAX_MESSAGE_CHARS:
        return f"note of {len(loaded.note)} characters or lines: {loaded.note[:120]!r}"
    for s in loaded.learned or ():
        values = (s.b0, s.slope, s.p00, s.p01, s.p11)
        if not all(isinstance(v, float) and math.isfinite(v) for v in values):
            return f"non-finite state loaded: {values}"
        if abs(s.b0) > limits.bias_dps or abs(s.slope) > limits.slope_dps_per_c or s.p00 > limits.p00:
            return f"implausible state loaded: {values}"
    return None


def test_learned_bias_state_files(tmp_path: Path) -> None:
    limits = state_file.StateLimits.of(TrackerConfig())
    learned = [AxisBias(b0=0.1 * i, slope=0.001, p00=0.01, p01=0.0, p11=1e-5, updates=5 + i)
               for i in range(3)]
    base = json.loads(state_file.dumps(STATE_SET_ID, STATE_AXES, learned))
    path, findings = tmp_path / "bias.json", Findings()
    rng = random.Random(SEED + 3)
    for mutant in mutants(base, count(150), SEED + 3):
        seal_state(mutant.tree)
        text = mutant.text(lambda t: json.dumps(t, indent=1))
        if rng.random() < 0.1:
            text = state_key_twice(text)
            mutant.done.append("a key given twice")
        path.write_text(text)
        findings.runs += 1
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error", RuntimeWarning)
                loaded = state_file.load(path, STATE_SET_ID, STATE_AXES, limits)
        except Exception as exc:
            findings.add(mutant, f"traceback {type(exc).__name__}: {str(exc)[:150]}")
            continue
        findings.outcome(loaded.note if loaded.refused else None)
        problem = state_problem(loaded, limits)
        if problem:
            findings.add(mutant, problem)
    findings.check()


@pytest.fixture(scope="module")
def table_case() -> Any:
    return own_clock_case(1, dwell_s=3.0)


def dump_table(tree: Any) -> str:
    """A table file from the mutated rows: each row's cells joined by commas, as a hand writes them."""
    def cell(v: Any) -> str:
        return v if isinstance(v, str) else repr(v)

    rows = tree.get("rows", []) if isinstance(tree, dict) else []
    rows = rows if isinstance(rows, list) else [rows]  # the rows swapped for one value
    lines = [",".join(map(cell, r)) if isinstance(r, list) else cell(r) for r in rows]
    header = tree.get("header", "") if isinstance(tree, dict) else ""
    head = ",".join(map(cell, header)) if isinstance(header, list) else cell(header)
    return "\n".join([head, *lines]) + "\n"


def test_table_reference_files(table_case: Any, tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """What ``calibrate --reference`` does with the table's file before calibrating: read, align, join.

    Mutations of cells, rows and header; one in five named ``.trc`` (a CAN log's suffix)."""
    lines = table_csv(table_case.table).splitlines()
    base = {"header": lines[0].split(","), "rows": [line.split(",") for line in lines[1:]]}
    rng, findings = random.Random(SEED + 4), Findings()
    for mutant in mutants(base, count(50), SEED + 4):
        path = tmp_path / ("table.trc" if rng.random() < 0.2 else "table.csv")
        path.write_text(mutant.text(dump_table))
        findings.runs += 1
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("error", RuntimeWarning)
                trace = read_table_trace(path, dbc=DBC)
                fit = align_reference(table_case.session.time_s, table_case.session.raw, trace)
                joined = join_reference(table_case.session.time_s, trace, fit)
            findings.outcome(None)
            if not np.isfinite(joined.ref_dps[joined.inside]).all():
                findings.add(mutant, "non-finite reference joined")
        except CanicalError as exc:
            findings.outcome(str(exc))
            if "\n" in str(exc) or len(str(exc)) > MAX_MESSAGE_CHARS:
                findings.add(mutant, f"refusal not one bounded line: {str(exc)[:120]!r}")
        except Exception as exc:
            findings.add(mutant, f"traceback {type(exc).__name__}: {str(exc)[:150]}")
        out = capsys.readouterr()
        if len((out.out + out.err).splitlines()) > 2:
            findings.add(mutant, f"{len((out.out + out.err).splitlines())} lines printed")
        path.unlink()
    findings.check()



def test_a_few_mutants_as_a_process(folder: Path) -> None:
    """The installed entry point as a separate process (``python -m canical``), on a few IMU set
    mutants: the exit status and stderr a shell or systemd sees, as in-process."""
    import subprocess
    import sys

    base = yaml.safe_load((folder / "imu-set.yaml").read_text())
    here = work(folder, "process")
    for mutant in mutants(base, 3, SEED + 5, most=2):
        seal_set(mutant.tree)
        path, out = here / "imu-set.yaml", here / "out.csv"
        path.write_text(mutant.text(dump_yaml))
        done = subprocess.run([sys.executable, "-m", "canical", "apply", str(path), str(folder / "drive.csv"),
                               "-o", str(out)], capture_output=True, text=True, timeout=120)
        assert "Traceback" not in done.stderr and done.returncode in (0, 2), done.stderr[-400:]
        if done.returncode == 2:
            assert refusal_problem(done.stderr) is None and not out.exists(), done.stderr
        out.unlink(missing_ok=True)
