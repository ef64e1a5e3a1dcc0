"""Every set file in the repository loads, writes back the bytes it was read from, and keeps its CRC.

Why: the set became typed records (issue 31); the file format, and so every set's id on the bus,
must not move. tests/data/sets holds sets written before that change (see
tests/support/set_corpus.py): every model kind, every term kind, the docs' example, IMU sets, and
sets whose terms leave optional keys out (as the daemon tests' fixtures write them).
"""

from __future__ import annotations

from pathlib import Path

import pytest
import yaml

from canical.sets import coefficient_file, imu_set
from canical.sets.coefficients import CoefficientSet

CORPUS = sorted((Path(__file__).parents[1] / "data" / "sets").glob("*.yaml"))


def _sets(text: str) -> tuple[object, tuple[CoefficientSet, ...]]:
    if "kind: imu-set" in text:
        imu = imu_set.loads(text)
        return imu, imu.axes
    cset = coefficient_file.loads(text)
    return cset, (cset,)


def test_the_corpus_has_every_model_kind_and_term_kind() -> None:
    from canical.models.kinds import ALL_KINDS
    from canical.sets.term_kinds import ALL

    sets = [c for p in CORPUS for c in _sets(p.read_text())[1]]
    assert {c.kind for c in sets} == set(ALL_KINDS)
    assert {t.spec for c in sets for t in c.terms} == set(ALL)
    assert any(t.keys is not None for c in sets for t in c.terms)  # terms that leave keys out


@pytest.mark.parametrize("path", CORPUS, ids=lambda p: p.name)
def test_a_set_file_round_trips_byte_for_byte_with_its_crc(path: Path) -> None:
    text = path.read_text()
    loaded, axes = _sets(text)
    written = imu_set.dumps(loaded) if isinstance(loaded, imu_set.ImuSet) else coefficient_file.dumps(loaded)
    assert yaml.safe_load(written)["crc32"] == yaml.safe_load(text)["crc32"]
    if "&id" in text:
        # YAML anchors: the writer shared one dict between axes; the content is the same, the
        # records are not shared after a load, so the text spells the value out.
        assert yaml.safe_load(written) == yaml.safe_load(text)
    else:
        assert written == text
    for cset in axes:
        assert coefficient_file.loads(coefficient_file.dumps(cset)) == cset


@pytest.mark.parametrize("path", [p for p in CORPUS if "kind: imu-set" not in p.read_text()],
                         ids=lambda p: p.name)
def test_keys_this_version_does_not_read_are_written_back_as_read(path: Path) -> None:
    """A newer version's key, or a field a kind does not read (knots on an offset term, as the
    device ignores them too), loads and is written back as read: the set keeps its CRC."""
    content = yaml.safe_load(path.read_text())
    content["model"]["colour"] = ["blue", 1]
    for term in content["terms"]:
        term["note"] = {"by": "hand"}
        if not term.get("knots"):
            term["knots"] = "anything"
    content["crc32"] = f"0x{coefficient_file.content_crc(content):08x}"
    cset = coefficient_file.from_content(content, "s.yaml")
    assert f"0x{coefficient_file.set_crc(cset):08x}" == content["crc32"]
    assert yaml.safe_load(coefficient_file.dumps(cset)) == content
