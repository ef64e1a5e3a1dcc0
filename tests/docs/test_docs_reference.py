"""The generated reference stays true to the code: configuration keys, set file fields, pages build."""

from __future__ import annotations

import sys
from pathlib import Path

import pytest

SCRIPTS = Path(__file__).resolve().parents[2] / "docs" / "scripts"
sys.path.insert(0, str(SCRIPTS))

import config_keys  # noqa: E402
import reference  # noqa: E402
import set_schema  # noqa: E402


def test_every_key_the_daemon_parser_accepts_is_documented_and_no_other():
    missing, stale = config_keys.undocumented_keys()
    assert not missing, (
        f"daemon_config accepts keys docs/scripts/config_keys.py does not list: {sorted(missing)}"
    )
    assert not stale, f"docs/scripts/config_keys.py lists keys daemon_config refuses: {sorted(stale)}"


def test_the_probe_sees_a_key_the_table_lacks(monkeypatch):
    """The check has teeth: a documented key taken out of the table is reported missing."""
    keys = tuple(k for k in config_keys.KEYS if k.key != "watch_period_s")
    monkeypatch.setattr(config_keys, "KEYS", keys)
    missing, _ = config_keys.undocumented_keys()
    assert missing == {"watch_period_s"}
    with pytest.raises(RuntimeError, match="watch_period_s"):
        reference.configuration_page()


@pytest.mark.parametrize("check", config_keys.default_checks(), ids=lambda c: c[0])
def test_documented_defaults_are_the_parsers(check):
    key, documented, actual = check
    assert documented == config_keys.as_yaml_value(actual), (
        f"{key}: docs say {documented}, parser gives {actual!r}"
    )


def _sets():
    from support.firmware_cases import ALL_TERMS, MODELS, model_set, term_set

    sets = [model_set(name) for name in MODELS]
    sets.append(term_set(tuple(ALL_TERMS)))  # every kind, the splines included
    return sets


def test_every_field_a_set_carries_is_documented_and_every_documented_field_occurs():
    from canical.files.yaml_text import parse_yaml
    from canical.sets import coefficient_file
    from canical.sets.signed_file import sign_text
    from canical.sets.signing import new_seed

    seen: set[str] = set()
    for cset in _sets():
        seen |= set(set_schema.key_paths(parse_yaml(coefficient_file.dumps(cset), "set")))
    signed, _ = sign_text(coefficient_file.dumps(_sets()[0]), "set", new_seed(), 1)  # `canical sign`'s fields
    seen |= set(set_schema.key_paths(parse_yaml(signed, "set")))
    documented = set_schema.documented_paths()
    assert not seen - documented, (
        f"set fields missing from docs/scripts/set_schema.py: {sorted(seen - documented)}"
    )
    assert not documented - seen, (
        f"docs/scripts/set_schema.py lists fields no set carries: {sorted(documented - seen)}"
    )


def test_term_fields_are_documented():
    from canical.sets.terms import TERM_FIELDS

    assert {f"terms[].{f}" for f in TERM_FIELDS} <= set_schema.documented_paths()


def test_reference_pages_name_every_command_frame_and_object():
    import cantools

    from canical.commands import COMMANDS

    pages = {
        "cli": reference.cli_page(),
        "frames": reference.frames_page(),
        "od": reference.object_dictionary_page(),
    }
    for name in COMMANDS:
        assert f"## canical {name}\n" in pages["cli"]
    for message in cantools.database.load_file(str(reference.ROOT / "dbc" / "canical.dbc")).messages:
        assert f"## {message.name}\n" in pages["frames"]
        for signal in message.signals:
            assert f"| `{signal.name}` |" in pages["frames"]
    assert "`0x2220`" in pages["od"] and "Active banks" in pages["od"]
