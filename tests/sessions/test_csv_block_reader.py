"""A block of rows handed to numpy's reader as a file parses as ``numpy.loadtxt`` of the same bytes,
cell for cell and bit for bit, and fails where it fails; without that reader, the same columns."""

from __future__ import annotations

import io

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canical.sessions import csv_chunks

CELLS = st.one_of(
    st.floats(allow_nan=False, allow_infinity=False).map(repr),
    st.integers(-10**12, 10**12).map(str),
    st.integers(-10**9, 10**9).map(lambda k: f"{k / 1e6:.9g}"),
    st.sampled_from(["1e5", "-.5", "5.", "+3", " 7 ", "2#x", "nan", "inf", "", "a", "1 2", '"4"', "0x1"]),
)


def loadtxt(block: bytes, usecols: list[int]) -> np.ndarray | str:
    try:
        return np.loadtxt(io.BytesIO(block), delimiter=",", ndmin=2, dtype=float, usecols=usecols)
    except (ValueError, IndexError) as exc:
        return type(exc).__name__


def fast(block: bytes, usecols: list[int]) -> np.ndarray | str:
    try:
        return csv_chunks._loadtxt(block, usecols)
    except (ValueError, IndexError) as exc:
        return type(exc).__name__


@settings(max_examples=300, deadline=None)
@given(st.lists(st.lists(CELLS, min_size=3, max_size=4), min_size=1, max_size=30),
       st.sampled_from([[0], [2], [0, 2], [1, 0]]))
def test_block_read_as_a_file_is_loadtxt(rows, usecols):
    assert csv_chunks._READ_FILE is not None  # this numpy has it: the fast way is the one tested
    block = "".join(",".join(r) + "\n" for r in rows).encode()
    expected, got = loadtxt(block, usecols), fast(block, usecols)
    if isinstance(expected, str) or isinstance(got, str):
        assert isinstance(expected, str) and isinstance(got, str)
    else:
        assert got.shape == expected.shape and got.tobytes() == expected.tobytes()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_columns_without_numpys_file_reader_are_the_same(tmp_path, monkeypatch, seed):
    rng = np.random.default_rng(seed)
    n = 30_000
    path = tmp_path / "s.csv"
    t, raw = np.arange(n) / 1000.0, rng.normal(0, 1e4, n).round(int(rng.integers(0, 6)))
    rows = "".join(f"{a!r},0,{b!r}\n" for a, b in zip(t.tolist(), raw.tolist(), strict=True))
    path.write_text("# sensor: X\ntime_s,ref_dps,raw\n" + rows)
    monkeypatch.setattr(csv_chunks, "CHUNK_BYTES", 50_000)
    fast_cols = csv_chunks.read_columns(path, ["time_s", "raw"]).columns
    monkeypatch.setattr(csv_chunks, "_READ_FILE", None)
    plain = csv_chunks.read_columns(path, ["time_s", "raw"]).columns
    assert fast_cols["raw"].tobytes() == plain["raw"].tobytes() == raw.tobytes()
    assert fast_cols["time_s"].tobytes() == plain["time_s"].tobytes() == t.tobytes()


@pytest.mark.parametrize("blank", ["\n", "  \n", " \t \n", "#note\n"])
@pytest.mark.parametrize("seed", [0, 1])
def test_rows_read_table_drops_or_refuses_send_the_block_to_the_rows(tmp_path, monkeypatch, blank, seed):
    """An empty row, one of spaces, a comment: the block reader reads or refuses as read_table."""
    from canical.errors import CanicalError
    from canical.sessions.csv_file import read_table

    rng = np.random.default_rng(seed)
    lines = [f"{i / 1000!r},0,{int(v)}\n" for i, v in enumerate(rng.integers(-500, 500, 3000))]
    for at in sorted(rng.integers(0, len(lines), 5).tolist(), reverse=True):
        lines.insert(at, blank)
    path = tmp_path / "s.csv"
    path.write_text("# sensor: X\ntime_s,ref_dps,raw\n" + "".join(lines))
    monkeypatch.setattr(csv_chunks, "CHUNK_BYTES", 4000)
    try:
        whole: dict[str, np.ndarray] | str = read_table(path, ["time_s", "raw"]).columns
    except CanicalError as exc:
        whole = str(exc)
    try:
        blocks: dict[str, np.ndarray] | str = csv_chunks.read_columns(path, ["time_s", "raw"]).columns
    except CanicalError as exc:
        blocks = str(exc)
    if isinstance(whole, str) or isinstance(blocks, str):
        assert blocks == whole
    else:
        assert {k: v.tobytes() for k, v in blocks.items()} == {k: v.tobytes() for k, v in whole.items()}
