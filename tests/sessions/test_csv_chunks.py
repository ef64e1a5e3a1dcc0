"""Columns read block by block are the columns ``read_table`` reads, and fail alike."""

from __future__ import annotations

import pytest

from canical.errors import CanicalError
from canical.sessions import csv_chunks
from canical.sessions.csv_file import read_session, read_table

TEXT = "# sensor: S\n# axis: z\ntime_s,ref_dps,raw,temp_c\n" + "".join(
    f"{i / 100:.2f},{(i // 50) * 3.0 - 30:g},{i * 7 % 101 - 50},{20 + i / 1000:.3f}\n" for i in range(700))


@pytest.fixture(autouse=True)
def small_blocks(monkeypatch):
    monkeypatch.setattr(csv_chunks, "CHUNK_BYTES", 257)


@pytest.mark.parametrize("text", [
    pytest.param(TEXT, id="plain"),
    pytest.param(TEXT.replace("\n", "\r\n"), id="crlf"),
    pytest.param(TEXT.replace("\n", "\n\n", 30), id="blank rows"),
    pytest.param(TEXT.replace("\n", "\r", 1), id="lone carriage return"),
    pytest.param(TEXT.rstrip("\n"), id="no last newline"),
])
def test_same_columns_as_read_table(tmp_path, text):
    path = tmp_path / "s.csv"
    path.write_bytes(text.encode())
    whole = read_table(path)
    blocks = csv_chunks.read_columns(path)
    assert blocks.meta == whole.meta and blocks.header == whole.header
    assert blocks.first_data_line == whole.first_data_line
    assert list(blocks.columns) == list(whole.columns)
    for name, values in whole.columns.items():
        assert blocks.columns[name].tobytes() == values.tobytes()
    assert csv_chunks.read_header(path) == whole.header
    assert read_session(path).raw.tobytes() == whole.columns["raw"].tobytes()


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_rows_far_shorter_after_the_first_block_enlarge_the_columns(tmp_path, seed):
    """The columns are sized from the first block's bytes per row: a file whose later rows are
    shorter holds more rows than that; they are all read, in order."""
    import numpy as np

    rng = np.random.default_rng(seed)
    long_rows = [f"{i / 1000:.9f},{rng.normal():.12f},{rng.integers(-10**9, 10**9)}" for i in range(300)]
    short_rows = [f"{300 + i},{i % 7},{i % 5}" for i in range(int(rng.integers(2000, 4000)))]
    path = tmp_path / "s.csv"
    path.write_text("time_s,ref_dps,raw\n" + "\n".join(long_rows + short_rows) + "\n")
    whole = read_table(path)
    blocks = csv_chunks.read_columns(path)
    for name, values in whole.columns.items():
        assert blocks.columns[name].tobytes() == values.tobytes()


@pytest.mark.parametrize("text", [
    pytest.param(TEXT, id="plain"),
    pytest.param(TEXT.replace("\n", "\r", 1), id="read whole"),
])
def test_converted_block_by_block_as_the_whole(tmp_path, text):
    """``convert`` sees the blocks in order and keeps what it returns: a running sum over the
    blocks is the running sum of the whole column."""
    import numpy as np

    path = tmp_path / "s.csv"
    path.write_bytes(text.encode())
    total = [0.0]
    seen = []

    def running(columns):
        seen.append(len(columns["raw"]))
        out = total[0] + np.cumsum(columns["raw"])
        total[0] = float(out[-1])
        return {"time_s": columns["time_s"], "sum": out}

    got = csv_chunks.read_columns(path, ["time_s", "raw"], convert=running)
    whole = read_table(path)
    assert list(got.columns) == ["time_s", "sum"]
    assert got.columns["time_s"].tobytes() == whole.columns["time_s"].tobytes()
    np.testing.assert_allclose(got.columns["sum"], np.cumsum(whole.columns["raw"]), rtol=0, atol=1e-9)
    assert sum(seen) == len(whole.columns["raw"]) and (len(seen) > 1) == ("\r" not in text)


@pytest.mark.parametrize("change", [
    lambda t: t.replace("\n4.0", "\n4.x", 1),
    lambda t: t.replace("\n5.00,", "\n5.00,,", 1),
    lambda t: t.replace("\n6.00,", "\ninf,", 1),
    lambda t: t.split("time_s")[0] + "time_s,raw,raw\n1,2,3\n",
    lambda t: "\n".join(t.split("\n")[:3]) + "\n",
    lambda t: "",
])
def test_same_errors_as_read_table(tmp_path, change):
    path = tmp_path / "s.csv"
    path.write_text(change(TEXT))
    with pytest.raises(CanicalError) as whole:
        read_table(path)
    with pytest.raises(CanicalError) as blocks:
        csv_chunks.read_columns(path)
    assert str(blocks.value) == str(whole.value)


def test_a_missing_file(tmp_path):
    with pytest.raises(CanicalError, match="file not found"):
        csv_chunks.read_columns(tmp_path / "none.csv")


def test_a_plain_block_is_tabs_newlines_and_space_to_tilde_only():
    import numpy as np

    plain = np.zeros(256, dtype=bool)
    plain[[9, 10]] = True
    plain[32:127] = True
    rng = np.random.default_rng(0)
    base = np.frombuffer(b"0.001,-0.1,24\n0.002,\t-0.2,33\n", dtype=np.uint8)
    for byte in range(256):
        for at in (0, 7, base.size - 1):
            buf = base.copy()
            buf[at] = byte
            block = buf.tobytes()
            got = csv_chunks._is_plain(block)
            assert got == bool(plain[buf].all()), (byte, at)
    for _ in range(200):
        buf = rng.choice(np.frombuffer(b"0123456789,.-e \t\n\r\x7f\x00\xc3", dtype=np.uint8), 64)
        block = buf.tobytes()
        assert csv_chunks._is_plain(block) == bool(plain[buf].all())
