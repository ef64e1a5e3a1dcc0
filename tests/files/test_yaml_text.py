"""YAML written by people, and by attackers: every defect one line, nothing a reader trips on later."""

from __future__ import annotations

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st

from canical.errors import CanicalError
from canical.files import yaml_text
from canical.files.yaml_text import parse_yaml


def refusal(text: str) -> str:
    with pytest.raises(CanicalError) as caught:
        parse_yaml(text, "f.yaml")
    message = str(caught.value)
    assert len(message.splitlines()) == 1 and len(message) < 200, message
    return message


def alias_bomb(levels: int = 9) -> str:
    lines = ['a0: &a0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]']
    for i in range(1, levels):
        lines.append(f"a{i}: &a{i} [" + ", ".join([f"*a{i - 1}"] * 9) + "]")
    return "\n".join(lines) + "\n"


def test_an_alias_bomb_is_refused_in_one_short_line() -> None:
    assert refusal(alias_bomb()) == "f.yaml: more than 100,000 values (aliases that expand without end?)"


@pytest.mark.parametrize(("text", "message"), [
    ("x: " + "9" * 5000, "f.yaml: a number with more than 20 digits"),
    ("x: " + "9" * 400, "f.yaml: a number with more than 20 digits"),
    ("x: [" + "[" * 990 + "]" * 990 + "]", "f.yaml: nested deeper than 32 levels"),
    ("fit:\n" + "".join("  " * (i + 1) + f"k{i}:\n" for i in range(200)) + "  " * 201 + "1\n",
     "f.yaml: nested deeper than 32 levels"),
    ("a: 1\nb: 2\na: 3\n", "f.yaml: key 'a' given twice at line 3"),
    ("axes:\n  z: {raw: A.B}\n  z: {raw: A.C}\n", "f.yaml: key 'z' given twice at line 3"),
    ("a: [1, 2\n", "f.yaml: not valid YAML at line 2"),
])
def test_what_no_canical_file_holds_is_refused(text: str, message: str) -> None:
    assert refusal(text) == message


def test_a_text_over_the_size_bound_is_refused_before_parsing() -> None:
    assert "larger than 4 MiB" in refusal("#" * (yaml_text.MAX_BYTES + 1))


def test_plain_data_merges_and_large_but_real_numbers_pass() -> None:
    text = "base: &b {x: 1}\nc:\n  <<: *b\n  y: 2\nid: 0x18FF3780\nbig: 18446744073709551615\nf: 1.0e+300\n"
    assert parse_yaml(text, "f.yaml") == {"base": {"x": 1}, "c": {"x": 1, "y": 2}, "id": 0x18FF3780,
                                          "big": 2**64 - 1, "f": 1e300}


@settings(max_examples=200, deadline=None)
@given(st.text(alphabet="ab:{}[]&*-!|>\n '\"0123456789.#<,", max_size=200))
def test_any_text_is_content_or_one_line(text: str) -> None:
    try:
        parse_yaml(text, "f.yaml")
    except CanicalError as exc:
        assert len(str(exc).splitlines()) == 1 and len(str(exc)) < 200
