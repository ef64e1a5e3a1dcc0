"""Means of k rows summed a column at a time are numpy's row means, bit for bit, signed zeros too."""

from __future__ import annotations

import numpy as np
import pytest

from canical.sessions import row_means
from canical.sessions.csv_chunks import read_head


@pytest.mark.parametrize("k", [1, 2, 3, 5, 7, 8, 13])
@pytest.mark.parametrize("seed", [0, 1, 2])
def test_column_sums_are_numpys_means(monkeypatch, tmp_path, k, seed):
    rng = np.random.default_rng(seed)
    n = 20 * k + int(rng.integers(0, k))
    values = rng.normal(0, 1, n) * rng.choice([1.0, 1e9, 1e-9], n)
    values[rng.integers(0, n, 5)] = -0.0
    values[: 2 * k] = -0.0  # a mean of negative zeros only
    path = tmp_path / "s.csv"
    path.write_text("time_s,raw\n" + "".join(f"{i},{v!r}\n" for i, v in enumerate(values.tolist())))
    head = read_head(path)
    assert head is not None
    got = {}
    for by_columns in (True, False):
        monkeypatch.setattr(row_means, "_BY_COLUMNS_BELOW", 8 if by_columns else 0)
        reducer = row_means._Reducer(head, n, k, "raw", None)
        reducer.add({"time_s": np.arange(n, dtype=float), "raw": values}, 0)
        table, means = reducer.finish()
        got[by_columns] = (table.columns["raw"].tobytes(), means.raw_low.tobytes(), means.raw_high.tobytes())
    assert got[True] == got[False]
    whole = values[: n - n % k].reshape(-1, k)
    assert got[True][0][: whole.shape[0] * 8] == whole.mean(axis=1).tobytes()
