"""Each term kind's record holds exactly the fields the kind reads: the set file's other fields
are null when the term is written, a field the kind does not read is refused when a term is
made in code, and a term cannot hold another kind's record."""

import pytest

from canical.sets.term_kinds import ALL, CHANNEL_DERIVATIVE, CHANNEL_LAG, CHANNEL_OFFSET
from canical.sets.term_params import Lag, OnChannel
from canical.sets.terms import Term, term_from_dict

#: Every optional field a term may carry, valid for any kind that reads it.
EVERY_FIELD = {"channel": "temp_c", "tau_s": 30.0, "threshold_raw": 2.0, "knots": [0.0, 1.0],
               "pieces": [[0.0, 1.0, 0.0, 0.0]]}


@pytest.mark.parametrize("kind", ALL, ids=[f"{k.kind}/{k.feature}" for k in ALL])
def test_a_term_holds_and_writes_only_what_its_kind_reads(kind) -> None:
    d = {"kind": kind.kind, "feature": kind.feature, "form": "bias", "coefficient": 0.5, "reference": 1.0,
         **EVERY_FIELD}
    term = term_from_dict(d)
    held = kind.record.field_names()
    assert type(term.params) is kind.record and set(term.params.fields()) == held
    written = term.to_dict()
    for key in ("channel", "tau_s", "threshold_raw"):
        assert written[key] == (d[key] if key in held else None)
    assert ("knots" in written) == ("knots" in held) == kind.needs_spline
    assert term.channel == (d["channel"] if kind.needs_channel else None)


def test_a_term_made_in_code_refuses_a_field_its_kind_does_not_read() -> None:
    with pytest.raises(TypeError):
        Term.of(CHANNEL_OFFSET, "bias", 0.0, channel="temp_c", tau_s=3.0)
    with pytest.raises(TypeError):
        Term.of(CHANNEL_LAG, "bias", 0.0, channel="temp_c")  # a lag without its τ


def test_a_term_cannot_hold_another_kinds_record() -> None:
    with pytest.raises(TypeError):
        Term(CHANNEL_LAG, "bias", 0.0, OnChannel("temp_c"))
    with pytest.raises(TypeError):
        Term(CHANNEL_OFFSET, "bias", 0.0, Lag(channel="temp_c", tau_s=3.0))


def test_owns_tells_the_kind() -> None:
    lag = Term.of(CHANNEL_LAG, "bias", 0.0, channel="temp_c", tau_s=3.0)
    assert CHANNEL_LAG.owns(lag) and not CHANNEL_DERIVATIVE.owns(lag)
    assert lag.params == Lag(channel="temp_c", tau_s=3.0)
