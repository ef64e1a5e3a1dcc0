"""The registry of term kinds is complete everywhere: a kind missing from any place fails here.

The C evaluator's ``TERM_SPECS`` table is read from ``firmware/canical_eval.c`` and must list
exactly the registry's kinds, with the registry's C identifier and required fields; every kind
is validated, evaluated (block and one-sample paths alike), compiled (bit for bit the
reference), described, has a block feature in the candidate search and a term in the shared
firmware cases.
"""

from __future__ import annotations

import re
import struct
import sys
from pathlib import Path

import numpy as np
import pytest

from canical.closed_loop.candidates import BLOCK_FEATURES
from canical.sets import term_kinds
from canical.sets.coefficients import CoefficientSet
from canical.sets.corrector import Corrector
from canical.sets.fast_corrector import COMPILED_TERMS, compile_corrector
from canical.sets.set_model import model_of
from canical.sets.term_kinds import ALL, TermKind, lookup
from canical.sets.terms import feature_values, term_from_dict

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT / "tests"))

from support.firmware_cases import TERMS  # noqa: E402

ROW = re.compile(r'\{\s*"(\w+)"\s*,\s*"(\w+)"\s*,\s*(\w+)\s*,\s*([^}]*)\}')
MODEL = {"kind": "segmented-inverse", "knots_raw": [-1000.0, 1000.0], "segment_points_dps": [-10.0, 10.0],
         "scale": 1000.0, "coefficients": [[0.1, 0.2, 0.003], [0.0, 0.25, 0.001], [0.2, 0.2, -0.002]],
         "smoothness": 1, "span_raw": [-30000.0, 30000.0], "out_of_span": "linear-extrapolation"}


def c_term_specs(source: str) -> set[tuple[str, str, str, frozenset[str]]]:
    """The rows of ``TERM_SPECS``: (kind, feature, code, needs flags)."""
    table = re.search(r"TERM_SPECS\[\]\s*=\s*\{(.*?)\n\};", source, re.S)
    assert table, "TERM_SPECS not found in canical_eval.c"
    rows = set()
    for kind, feature, code, needs in ROW.findall(table.group(1)):
        flags = frozenset(f.strip() for f in needs.split("|")) - {"0u", ""}
        rows.add((kind, feature, code, flags))
    return rows


#: The kinds the C evaluator evaluates (the others it refuses: tested below).
IN_C = tuple(k for k in ALL if k.c_name is not None)


def registry_specs(kinds: tuple[TermKind, ...] = IN_C) -> set[tuple[str, str, str | None, frozenset[str]]]:
    def flags(k: TermKind) -> frozenset[str]:
        named = {"NEEDS_CHANNEL": k.needs_channel, "NEEDS_TAU": k.needs_tau,
                 "NEEDS_THRESHOLD": k.needs_threshold, "NEEDS_SPLINE": k.needs_spline}
        return frozenset(name for name, needed in named.items() if needed)

    return {(k.kind, k.feature, k.c_name, flags(k)) for k in kinds}


def test_c_table_lists_exactly_the_registry() -> None:
    assert c_term_specs((ROOT / "firmware" / "canical_eval.c").read_text()) == registry_specs()


def test_c_table_check_fails_when_a_kind_is_missing() -> None:
    source = (ROOT / "firmware" / "canical_eval.c").read_text()
    without_gated = "\n".join(ln for ln in source.splitlines() if '{"channel", "gated"' not in ln)
    assert c_term_specs(without_gated) != registry_specs()
    assert c_term_specs(source) != registry_specs(IN_C[:-1])


def test_c_identifiers_are_defined_in_the_evaluator() -> None:
    source = (ROOT / "firmware" / "canical_eval.c").read_text()
    for k in IN_C:
        assert re.search(rf"\b{k.c_name}\b\s*=|\b{k.c_name},", source), k


def test_lookup_and_features() -> None:
    assert len({k.key for k in ALL}) == len(ALL)
    for k in ALL:
        assert lookup(*k.key) is k
        assert k.feature in term_kinds.FEATURES[k.kind]
    assert lookup("channel", "nope") is None


def _term_dict(kind: TermKind, form: str) -> dict[str, object]:
    d: dict[str, object] = {"kind": kind.kind, "feature": kind.feature, "form": form, "coefficient": 0.0123}
    if kind.needs_channel:
        d["channel"] = "temp_c"
        d["reference"] = 25.0
    if kind.needs_tau:
        d["tau_s"] = 3.0
    if kind.needs_threshold:
        d["threshold_raw"] = 0.3 if kind.needs_channel else 200.0
    if kind.needs_spline:  # a flat-ended bump over the channel's range, and one knot inside it
        d["knots"] = [22.0, 25.0, 28.5]
        d["pieces"] = [[0.5, -0.25, 0.125, -0.0625], [-0.3, 0.1, 0.05, -0.01]]
    return d


@pytest.mark.parametrize("kind", ALL, ids=lambda k: f"{k.kind}-{k.feature}")
def test_every_kind_is_validated_evaluated_compiled_and_described(kind: TermKind) -> None:
    for field in ("tau_s", "threshold_raw"):  # a required field missing is refused
        needed = kind.needs_tau if field == "tau_s" else kind.needs_threshold
        if needed:
            d = _term_dict(kind, "bias")
            del d[field]
            with pytest.raises(ValueError, match=field):
                term_from_dict(d)
    rng = np.random.default_rng(1)
    n = 400
    raw = np.rint(3000.0 * np.sin(np.arange(n) / 30.0) + rng.normal(0.0, 50.0, n))
    inputs = {"time_s": np.arange(n) / 10.0, "temp_c": 25.0 + np.cumsum(rng.normal(0.0, 0.1, n))}
    for form in ("bias", "scale"):
        term = term_from_dict(_term_dict(kind, form))
        assert term.spec is kind
        assert kind.key in COMPILED_TERMS
        assert isinstance(term.describe(), str) and term.describe()
        assert set(term.input_names) <= set(inputs)
        x = feature_values(term, inputs, raw, raw - 12.5)
        assert x.shape == (n,) and np.isfinite(x).all()
        cset = CoefficientSet("s", "z", 12.5, model_of(MODEL), (term_from_dict(_term_dict(kind, form)),))
        block, _ = Corrector(cset).correct(raw, inputs)
        reference, compiled_corrector = Corrector(cset), Corrector(cset)
        compiled = compile_corrector(compiled_corrector)
        assert compiled is not None
        for i in range(n):
            row = {k: float(v[i]) for k, v in inputs.items()}
            one, _ = reference.correct_one(raw[i], row)
            fast, _ = compiled(raw[i], row)
            assert struct.pack("<d", one) == struct.pack("<d", fast)
            assert one == pytest.approx(block[i], rel=1e-12, abs=1e-12)


def test_every_kind_has_a_block_feature_and_a_firmware_case() -> None:
    assert set(BLOCK_FEATURES) == set(ALL)
    assert {lookup(t["kind"], t["feature"]) for t in TERMS.values()} == set(IN_C)


def test_a_kind_missing_a_part_of_its_contract_cannot_be_made() -> None:
    """The base class is abstract: a kind without its wording (or maths, or code) fails when the
    registry makes it, at import, not when a report first asks for it."""

    class NoWording(term_kinds.TimeKind):
        feature = "nowording"
        c_name = None

        def values(self, term, inputs, raw, dv):
            return raw

        def one(self, term, tracker, raw, dv, inputs):
            return raw

        def code_x(self, term, names):
            return "raw"

    with pytest.raises(TypeError, match="describe"):
        NoWording()


def test_the_kinds_kept_between_frames_are_those_with_x_of_their_input_alone() -> None:
    kept = {k.key for k in ALL if k.kept}
    assert kept == {("channel", "offset"), ("channel", "square"), ("time", "warmup"), ("time", "linear")}
    assert all(isinstance(k, term_kinds.KeptCode) == k.kept for k in ALL)
