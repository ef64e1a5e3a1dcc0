"""``canical apply`` block by block writes what the whole file at once writes, byte for byte.

The streamed path (``apply_stream``) is compared with the in-memory path (``apply_table``, the
code ``apply`` ran before it streamed, unchanged) on the same files, in blocks of a few hundred
bytes so that every file spans many blocks: stateful terms across the blocks' edges, rows that
are not plain ASCII lines, and the errors a bad file gives.
"""

from __future__ import annotations

import argparse
import contextlib
import sys
from pathlib import Path

import numpy as np
import pytest

from canical.commands import apply as apply_command
from canical.commands.cli import main
from canical.errors import CanicalError
from canical.sessions import csv_chunks
from canical.sets import coefficient_file
from canical.sets.corrector import Corrector

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "sets"))
from test_terms import extended_set  # every kind of term, the stateful ones too


@pytest.fixture(autouse=True)
def small_blocks(monkeypatch):
    monkeypatch.setattr(csv_chunks, "CHUNK_BYTES", 300)


def session_text(n: int = 400, seed: int = 0) -> str:
    rng = np.random.default_rng(seed)
    raw = np.cumsum(rng.normal(0, 300, n)).round()
    temp = 25 + np.cumsum(rng.normal(0, 0.3, n))
    supply = rng.uniform(4.5, 5.5, n)
    time_s = np.cumsum(rng.uniform(0.001, 0.05, n))
    rows = [f"{t:.4f},{r:.0f},{c:.3f},{v:.4f},{w:.2f}" for t, r, c, v, w in
            zip(time_s, raw, temp, supply, rng.normal(0, 30, n), strict=True)]
    return "# sensor: S\n# axis: z\ntime_s,raw,temp_c,supply_v,ref_dps\n" + "\n".join(rows) + "\n"


def run_both(tmp_path: Path, text: str | bytes) -> tuple[bytes | str, bytes | str]:
    """The streamed and the in-memory outputs of the same file (or their one-line errors)."""
    cset = tmp_path / "set.yaml"
    coefficient_file.save(cset, extended_set())
    src = tmp_path / "in.csv"
    src.write_bytes(text if isinstance(text, bytes) else text.encode())
    outs: list[bytes | str] = []
    for name in ("stream", "table"):
        out = tmp_path / f"{name}.csv"
        args = argparse.Namespace(coefficients=str(cset), input=str(src), output=str(out), raw_column="raw",
                                  sensor=None, track_bias=False)
        corrector = Corrector(coefficient_file.load(cset))
        try:
            if name == "stream":
                apply_command.apply_set(args)
            else:
                apply_command.apply_table(args, corrector)
            outs.append(out.read_bytes())
        except CanicalError as exc:
            outs.append(str(exc))
    return outs[0], outs[1]


def test_stateful_terms_across_many_blocks(tmp_path):
    stream, table = run_both(tmp_path, session_text())
    assert csv_chunks.read_head(tmp_path / "in.csv") is not None  # so apply streamed it
    assert isinstance(stream, bytes)
    assert stream.count(b"\n") == 403
    assert stream == table


@pytest.mark.parametrize("change", [
    pytest.param(lambda t: t.replace("\n", "\r\n"), id="crlf"),
    pytest.param(lambda t: t.replace("\n", "\r", 1), id="a lone carriage return"),
    pytest.param(lambda t: t.replace("\n", "\n\n", 40), id="blank rows"),
    pytest.param(lambda t: t.replace("\n", "\n  \t\n", 60), id="blank rows of spaces"),
    pytest.param(lambda t: t.rstrip("\n"), id="no newline at the end"),
    pytest.param(lambda t: t.replace("# axis: z", "# axis: z\n# operator: Jörg"), id="non-ascii metadata"),
    pytest.param(lambda t: t.replace("\n1", "\n 1", 30), id="leading spaces"),
    pytest.param(lambda t: t.replace(",", ",ü", 2).replace("ref_dps\n", "ref_dps\n", 1), id="non-ascii cell"),
])
def test_files_that_are_not_plain_lines(tmp_path, change):
    stream, table = run_both(tmp_path, change(session_text()))
    assert stream == table


@pytest.mark.parametrize("change", [
    pytest.param(lambda t: t.replace("\n2", "\nx2", 1), id="not a number"),
    pytest.param(lambda t: t.replace("\n5", "\n1,2\n5", 1), id="short row"),
    pytest.param(lambda t: "\n".join(t.split("\n", 3)[:3]) + "\n\n  \n", id="no data rows"),
    pytest.param(lambda t: t.replace("temp_c", "temp"), id="missing column"),
    pytest.param(lambda t: t.replace("\n3", "\nnan", 1), id="not finite"),
])
def test_bad_files_give_the_same_error(tmp_path, change):
    stream, table = run_both(tmp_path, change(session_text()))
    assert isinstance(table, str)
    assert stream == table


def test_the_command_streams_and_refuses_what_it_refused(tmp_path, capsys):
    cset = tmp_path / "set.yaml"
    coefficient_file.save(cset, extended_set())
    src = tmp_path / "in.csv"
    src.write_text(session_text())
    assert main(["apply", str(cset), str(src), "-o", str(tmp_path / "o.csv")]) == 0
    assert "apply: 400 rows corrected" in capsys.readouterr().out
    src.write_text(session_text().replace("# sensor: S", "# sensor: T"))
    assert main(["apply", str(cset), str(src), "-o", str(tmp_path / "p.csv")]) == 2
    assert not (tmp_path / "p.csv").exists()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_late_bad_block_leaves_no_output(tmp_path, seed):
    """Blocks before the bad one were handed to the writing thread: none of them is kept."""
    text = session_text(n=600, seed=seed)
    lines = text.split("\n")
    lines[500 + seed] = "x" + lines[500 + seed]
    stream, table = run_both(tmp_path, "\n".join(lines))
    assert isinstance(stream, str) and stream == table
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.csv", "set.yaml"]


def test_a_failed_write_stops_the_run_and_leaves_no_output(tmp_path, monkeypatch):
    from canical.files import atomic_file  # apply imports atomic_writer where it is used: patched here

    opened = atomic_file.atomic_writer
    writes = {"n": 0}

    class Failing:
        def __init__(self, handle):
            self.handle = handle

        def write(self, data):
            writes["n"] += 1
            if writes["n"] == 4:
                raise OSError(28, "No space left on device")
            return self.handle.write(data)

    @contextlib.contextmanager
    def failing_writer(path, mode="w"):
        with opened(path, mode) as handle:
            yield Failing(handle)

    monkeypatch.setattr(atomic_file, "atomic_writer", failing_writer)
    with pytest.raises(OSError, match="No space"):
        run_both(tmp_path, session_text(n=600))
    assert 4 <= writes["n"] <= 5  # stopped at the next block, not at the end
    assert sorted(p.name for p in tmp_path.iterdir()) == ["in.csv", "set.yaml"]
