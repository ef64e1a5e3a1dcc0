"""Cells appended by numpy are the text Python's ``f"{x:.6f}"`` and ``int(flag)`` give."""

from __future__ import annotations

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canical.sessions.fixed_cells import append_cells, fixed6_cells, flag_cells


def python_rows(rows: list[str], values: list[float], flags: list[bool]) -> bytes:
    return "".join(f"{r},{v:.6f},{int(f)}\n" for r, v, f in zip(rows, values, flags, strict=True)).encode()


def numpy_rows(rows: list[str], values: list[float], flags: list[bool]) -> bytes:
    text = "".join(r + "\n" for r in rows).encode()
    return append_cells(text, [fixed6_cells(np.array(values, dtype=float)), flag_cells(np.array(flags))])


VALUES = st.one_of(st.floats(), st.floats(-1e3, 1e3), st.integers(-2**20, 2**20).map(lambda k: k / 128),
                   st.integers(-10**9, 10**9).map(lambda k: k / 1e6 + 5e-7))


@settings(max_examples=300, deadline=None)
@given(st.lists(st.tuples(st.text("0123456789.,-ab ", max_size=12), VALUES, st.booleans()), max_size=40))
def test_same_text_as_python(cells):
    rows, values, flags = ([c[i] for c in cells] for i in range(3))
    assert numpy_rows(rows, values, flags) == python_rows(rows, values, flags)


def test_edges_of_the_format():
    values = [0.0, -0.0, -1e-9, 5e-7, -5e-7, 1.5e-6, 2.5e-6, 1 / 128, -3 / 128, 0.9999995, 999999.9999995,
              1e15, -1e20, float("nan"), float("inf"), -float("inf"), 5e-324, 123.456789]
    rows = [f"r{i}" for i in range(len(values))]
    flags = [i % 2 == 0 for i in range(len(values))]
    assert numpy_rows(rows, values, flags) == python_rows(rows, values, flags)


def test_several_columns_and_no_rows():
    v = np.array([1.25, -2.0])
    cells = [fixed6_cells(v), flag_cells(np.array([True, False])), fixed6_cells(-v)]
    assert append_cells(b"a\nb\n", cells) == b"a,1.250000,1,-1.250000\nb,-2.000000,0,2.000000\n"
    assert append_cells(b"", [fixed6_cells(np.array([])), flag_cells(np.array([], dtype=bool))]) == b""


@settings(max_examples=200, deadline=None)
@given(st.lists(st.tuples(st.text("0123456789.,-ab \t", max_size=60), VALUES, st.booleans()), max_size=40))
def test_padded_and_byte_offset_ways_agree(cells):
    """A block of rows of very different lengths takes the byte-offset way: the same text."""
    from canical.sessions import fixed_cells

    rows, values, flags = ([c[i] for c in cells] for i in range(3))
    expected = python_rows(rows, values, flags)
    assert numpy_rows(rows, values, flags) == expected
    saved = fixed_cells._PADDED_AT_MOST
    try:
        fixed_cells._PADDED_AT_MOST = -1  # never padded: every block placed byte by byte
        assert numpy_rows(rows, values, flags) == expected
    finally:
        fixed_cells._PADDED_AT_MOST = saved


def test_a_long_row_among_short_ones():
    rows = ["1,2"] * 5000 + ["x" * 20000] + ["3"] * 5000
    values = list(np.linspace(-1234.5, 98765.4321, len(rows)))
    flags = [i % 3 == 0 for i in range(len(rows))]
    assert numpy_rows(rows, values, flags) == python_rows(rows, values, flags)


@pytest.mark.parametrize("seed", [0, 1, 2, 3])
@pytest.mark.parametrize("width", range(1, 10))
def test_every_width_of_whole_part_as_python(seed, width):
    """Whole parts of 1 to 9 digits (two words a row up to 8, columns beyond), digits at the
    powers of ten, signs, negative zero, a value Python formats itself among them."""
    rng = np.random.default_rng(seed)
    top = 10.0**width
    values = np.concatenate([
        rng.uniform(-top, top, 300),
        [10.0**k for k in range(width)], [-(10.0**k) + 5e-7 for k in range(width)],
        [top - 1e-3, -(top - 1e-3), -0.0, 0.0, -4e-7, 4e-7, 2.5e-6, float("nan")],
    ])
    rows = [f"r{i}" for i in range(len(values))]
    flags = [bool(i % 2) for i in range(len(values))]
    assert numpy_rows(rows, values.tolist(), flags) == python_rows(rows, values.tolist(), flags)
