"""Daemon configurations as an attacker or a typo writes them: one bounded line, never a traceback.

200 mutations of the deployable example gave 13 tracebacks (OverflowError for a huge
status_period_s, TypeError sorting own_layout.ids' mixed keys), refusals over several lines (an
input name with a newline) or of millions of characters (an alias bomb echoed), and accepted
what was wrong (a duplicate key's last value, "1_0" read as 10, two axes on one signal).
"""

from __future__ import annotations

import copy
from pathlib import Path

import pytest
import yaml
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from support.daemon_fixtures import write_config, write_sets

from canical.bus.daemon_config import load_config
from canical.errors import MAX_MESSAGE_CHARS, CanicalError


@pytest.fixture(scope="module")
def base(tmp_path_factory) -> tuple[Path, dict]:
    folder = tmp_path_factory.mktemp("cfg")
    write_sets(folder)
    path = write_config(folder, "can0")
    return folder, yaml.safe_load(path.read_text())


def refusal(folder: Path, content: dict | str) -> str:
    path = folder / "fuzz.yaml"
    path.write_text(content if isinstance(content, str) else yaml.safe_dump(content, sort_keys=False))
    with pytest.raises(CanicalError) as caught:
        load_config(path)
    message = str(caught.value)
    assert "\n" not in message and len(message) <= MAX_MESSAGE_CHARS, message
    return message


@pytest.mark.parametrize(("change", "words"), [
    (lambda c: c.update(status_period_s=10**400), "a number with more than 20 digits"),
    (lambda c: c.update(status_period_s=float("inf")), "status_period_s: must be a positive number"),
    (lambda c: c.update(status_period_s=-1), "status_period_s: must be a positive number"),
    (lambda c: c.update(own_layout={"id": 0x298, "ids": {"A": 1, 2: 3}}), "own_layout.ids"),
    (lambda c: c.update(j1939={"source_address": "1_0"}), "must be 'any' or a source address 0..253"),
    (lambda c: c["inputs"].update({"bad\nname": {"signal": "IMU_RAW.Temperature", "max_age_s": 1}}),
     "inputs.bad name"),
    (lambda c: c["axes"].update(y={"raw": "GyroRawX"}), "axes.y.raw: signal GyroRawX is axis x's already"),
])
def test_named_defects_are_one_bounded_line(base, change, words: str) -> None:
    folder, content = base
    mutated = copy.deepcopy(content)
    change(mutated)
    assert words in refusal(folder, mutated)


def test_an_alias_bomb_and_a_duplicate_key_are_refused(base) -> None:
    folder, content = base
    text = yaml.safe_dump(content, sort_keys=False)
    bomb = 'x0: &x0 ["lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol", "lol"]\n' + "".join(
        f"x{i}: &x{i} [" + ", ".join([f"*x{i - 1}"] * 9) + "]\n" for i in range(1, 9))
    assert "aliases that expand without end" in refusal(folder, bomb + text)
    twice = text + "status_period_s: 1\nstatus_period_s: 2\n"
    assert "key 'status_period_s' given twice" in refusal(folder, twice)


LEAVES = st.one_of(
    st.none(), st.booleans(), st.integers(-(10**30), 10**30), st.floats(allow_nan=True),
    st.text(max_size=12), st.lists(st.integers(-5, 5), max_size=3),
    st.dictionaries(st.one_of(st.text(max_size=4), st.integers(0, 3)), st.integers(0, 3), max_size=3))


def paths_of(value, prefix=()):
    yield prefix
    if isinstance(value, dict):
        for k, v in value.items():
            yield from paths_of(v, (*prefix, k))


@settings(max_examples=200, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(st.data())
def test_any_mutation_loads_or_is_one_bounded_line(base, data) -> None:
    folder, content = base
    mutated = copy.deepcopy(content)
    for _ in range(data.draw(st.integers(1, 3))):
        path = data.draw(st.sampled_from([p for p in paths_of(mutated) if p]))
        node = mutated
        for key in path[:-1]:
            node = node[key]
        if data.draw(st.booleans()):
            node[path[-1]] = data.draw(LEAVES)
        else:
            del node[path[-1]]
    target = folder / "fuzz.yaml"
    target.write_text(yaml.safe_dump(mutated, sort_keys=False))
    try:
        load_config(target)
    except CanicalError as exc:
        assert "\n" not in str(exc) and len(str(exc)) <= MAX_MESSAGE_CHARS


@pytest.mark.parametrize("name", ["x" * 5000, "a\x00b"])
def test_a_path_the_system_cannot_look_up_is_one_line(base, name: str) -> None:
    """The fuzzer's finding: a 5,000-character ``dbc:`` raised OSError (File name too long)."""
    folder, content = base
    mutated = copy.deepcopy(content)
    mutated["dbc"] = name
    assert "dbc: file" in refusal(folder, mutated) and "not found" in refusal(folder, mutated)


def test_a_coefficients_path_the_system_cannot_look_up_is_one_line(base, capsys) -> None:
    """The fuzzer's finding: a 5,000-character ``axes.z.coefficients`` raised OSError (File name
    too long) in serve --check."""
    from canical.commands.cli import main

    folder, content = base
    mutated = copy.deepcopy(content)
    mutated["axes"]["z"]["coefficients"] = "x" * 5000
    path = folder / "long.yaml"
    path.write_text(yaml.safe_dump(mutated, sort_keys=False))
    assert main(["serve", "--config", str(path), "--check"]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "coefficient file not found" in err and len(err) < 500, err
