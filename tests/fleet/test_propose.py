"""``fleet analyse --propose-sets``: the sensors whose field slope is significant get their set plus
the field-learned temperature term (``channel``/``offset`` and ``square`` bias terms on
``temp_c``), as set files that load and sign; the others are listed unchanged; a signed set's
successor is unsigned and a line says to sign it."""

from __future__ import annotations

import contextlib
import csv
import dataclasses
import io
import math
from pathlib import Path

import numpy as np
import pytest

from canical.commands.cli import main
from canical.sets import coefficient_file, signed_file
from canical.sets.coefficients import CoefficientSet

VEHICLES, DAYS, SEED = 40, 20, 1
SETS = Path(__file__).parents[1] / "data" / "sets"
SIGNED = "B25-00003"  # one sensor's set is signed
MERGED = "D26-00007"  # one sensor's set already has a temp_c term (daemon-x's, moved to z)


def rows(path: Path) -> dict[str, dict[str, str]]:
    return {r["sensor_id"]: r for r in csv.DictReader(path.open())}


def write_sets(truth: dict[str, dict[str, str]], folder: Path, key: Path) -> None:
    """A set per simulated sensor: daemon-z's model (no terms) under its id; one has a term already."""
    folder.mkdir()
    plain = coefficient_file.load(SETS / "daemon-z.yaml")
    termed = coefficient_file.load(SETS / "daemon-x.yaml")
    for sensor in truth:
        base = termed if sensor == MERGED else plain
        cset = dataclasses.replace(base, sensor_id=sensor, axis="z")
        coefficient_file.save(folder / f"{sensor}.yaml", cset)
    assert main(["sign", str(folder / f"{SIGNED}.yaml"), "--key", str(key)]) == 0


@pytest.fixture(scope="module")
def proposed(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path, Path, str]:
    """The fleet's folder, the old sets, the new ones and what the command printed."""
    root = tmp_path_factory.mktemp("propose")
    assert main(["simulate", "fleet", "--vehicles", str(VEHICLES), "--days", str(DAYS), "--seed", str(SEED),
                 "-o", str(root / "logs")]) == 0
    assert main(["fleet", "ingest", str(root / "logs"), "-o", str(root / "dataset")]) == 0
    assert main(["keygen", str(root / "lab")]) == 0
    write_sets(rows(root / "logs" / "truth.csv"), root / "sets", root / "lab.key")
    out = io.StringIO()
    with contextlib.redirect_stdout(out):
        assert main(["fleet", "analyse", str(root / "dataset"), "--report-dir", str(root / "r"),
                     "--propose-sets", str(root / "sets"), "-o", str(root / "new")]) == 0
    return root / "logs", root / "sets", root / "new", out.getvalue()


def _field_term(cset: CoefficientSet, feature: str = "offset") -> list[float]:
    wanted = ("channel", feature, "bias", "temp_c", 25.0)
    return [t.coefficient for t in cset.terms
            if (t.kind, t.feature, t.form, t.channel, t.reference) == wanted]


def _other_terms(cset: CoefficientSet) -> list[object]:
    field = ("channel", "temp_c", 25.0)
    return [t for t in cset.terms
            if not ((t.kind, t.channel, t.reference) == field and t.feature in ("offset", "square"))]


def test_significant_sensors_get_their_set_plus_the_field_term(
        proposed: tuple[Path, Path, Path, str]) -> None:
    logs, old, new, _ = proposed
    truth, table = rows(logs / "truth.csv"), rows(new / "proposals.csv")
    assert sorted(table) == sorted(truth)
    for sensor, row in table.items():
        slope, se = float(row["slope_dps_per_c"]), float(row["slope_se"])
        significant = abs(slope) > 3 * se
        assert (row["outcome"] == "proposed") == significant, sensor
        if not significant:
            assert not (new / f"{sensor}-z.yaml").exists()
            continue
        before = coefficient_file.load(old / f"{sensor}.yaml")
        after = coefficient_file.load(new / f"{sensor}-z.yaml")
        gain = float(before.rate_model().slope(np.array([0.0]))[0])  # type: ignore[union-attr]
        previous = _field_term(before)
        (coefficient,) = _field_term(after)
        # the line, fitted where the evidence is: the slope over the gain at rest within the
        # model's curvature there (test_field_term.py checks the fit itself)
        assert math.isclose((coefficient - sum(previous)) * gain, slope, rel_tol=0.03)
        assert len(_field_term(after, "square")) <= 1
        assert _other_terms(after) == _other_terms(before) and after.model == before.model
        evidence = after.fit["field_evidence"]
        assert evidence["within_sigma_after_dps"] < evidence["within_sigma_before_dps"]
        # the term learned is the truth's slope within its uncertainty
        assert abs(slope - float(truth[sensor]["slope_dps_per_c"])) < 4 * se
    assert sum(r["outcome"] == "proposed" for r in table.values()) >= len(truth) // 2
    assert table[MERGED]["outcome"] == "proposed"  # its temp_c term's coefficient changed, no second term


def test_the_signed_sets_successor_is_unsigned_and_signs(proposed: tuple[Path, Path, Path, str]) -> None:
    _, old, new, printed = proposed
    assert signed_file.read_set_file(old / f"{SIGNED}.yaml").signed.record is not None
    fresh = new / f"{SIGNED}-z.yaml"
    assert signed_file.read_set_file(fresh).signed.record is None
    assert "were signed and the new ones are not: sign each" in printed
    assert main(["sign", str(fresh), "--key", str(old.parent / "lab.key")]) == 0
    assert signed_file.read_set_file(fresh).signed.record is not None
    md = (new / "proposals.md").read_text()
    assert "## Unchanged" in md and "sign each" in md


def test_propose_sets_needs_its_output_and_real_sets(proposed: tuple[Path, Path, Path, str], tmp_path: Path,
                                                     capsys: pytest.CaptureFixture[str]) -> None:
    logs, old, _, _ = proposed
    data = logs.parent / "dataset"
    assert main(["fleet", "analyse", str(data), "--report-dir", str(tmp_path / "r"),
                 "--propose-sets", str(old)]) == 2
    assert "--propose-sets SETS and -o NEW go together" in capsys.readouterr().err
    assert main(["fleet", "analyse", str(data), "--report-dir", str(tmp_path / "r"),
                 "--propose-sets", str(tmp_path / "none"), "-o", str(tmp_path / "n")]) == 2
    err = capsys.readouterr().err
    assert "no such set file or folder" in err and "Traceback" not in err
