"""Seeded mutations of parsed files (sets, configurations, state files) for the fuzz tests.

Why on the parsed tree, then written out with the CRC recomputed: a mutation of the bytes is
refused by the CRC and never reaches the checks behind it; a mutation of the content, sealed
again, is what someone who can recompute a CRC writes. Some mutations are text no tree can
hold once dumped (a 5,000-digit number, nesting 1,000 deep): the tree carries a placeholder
string and :meth:`Mutant.text` puts the raw text in its place after dumping.
"""

from __future__ import annotations

import copy
import os
import random
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from typing import Any

#: How many mutations each surface gets: a few hundred in all by default; CANICAL_FUZZ_SCALE=20
#: (say) for a long run, CANICAL_FUZZ_SEED to draw other mutations.
SCALE = float(os.environ.get("CANICAL_FUZZ_SCALE", "1"))
SEED = int(os.environ.get("CANICAL_FUZZ_SEED", "34"))

#: Numbers that break arithmetic or its readers: huge, tiny, negative, overflowing, NaN-ish text.
NUMBERS: tuple[Any, ...] = (
    1e308, -1e308, 1.7976931348623157e308, 1e-300, -1e-300, 5e-324, 0, 0.0, -1, -1.0, 2**63, -(2**63),
    10**400, 2**1024, 1.2e21, 1e150, 100.0, -100.0, float("nan"), float("inf"), float("-inf"),
    "nan", ".nan", "NaN", "inf", "-.inf", "1e999", "1_0", "0x1p3", "", " ", "1,5", "١٢", True, False, None,
)
#: Raw text for placeholders: what a dumper never writes but a hand or an attacker does.
RAW_TEXTS: tuple[str, ...] = (
    "9" * 5000, "-" + "9" * 400, "1e99999", "0." + "0" * 400 + "1", "[" * 1000 + "]" * 1000,
    "[" * 990 + "1" + "]" * 990, "{a: " * 200 + "1" + "}" * 200, "&a [*a, *a]", "!!python/object:os.system x",
    "\"\\ud800\"", "'a\nb'",
)
PLACEHOLDER = "@@RAW{}@@"


@dataclass
class Mutant:
    """A mutated tree, the raw texts its placeholders stand for, and what was done (for messages)."""

    tree: Any
    raw: dict[str, str] = field(default_factory=dict)
    done: list[str] = field(default_factory=list)

    def text(self, dump: Callable[[Any], str]) -> str:
        """The tree dumped, each placeholder (quoted as the dumper quotes it) replaced by its text."""
        out = dump(self.tree)
        for key, raw in self.raw.items():
            for quoted in (f"'{key}'", f'"{key}"', key):
                out = out.replace(quoted, raw)
        return out


def paths(tree: Any, prefix: tuple[Any, ...] = ()) -> Iterator[tuple[Any, ...]]:
    """Every path to a node (the root excluded), containers and leaves, at most 12 levels down
    (inside nesting a mutation made, another would only outgrow the dumper's recursion)."""
    if len(prefix) >= 12:
        return
    items = tree.items() if isinstance(tree, dict) else enumerate(tree) if isinstance(tree, list) else ()
    for key, value in items:
        yield (*prefix, key)
        yield from paths(value, (*prefix, key))


def _parent(tree: Any, path: tuple[Any, ...]) -> Any:
    node = tree
    for key in path[:-1]:
        node = node[key]
    return node


def _swap_type(value: Any, rng: random.Random) -> Any:
    """Another type for the same place: a mapping as a list, a list as a mapping, a number as text."""
    if isinstance(value, dict):
        return rng.choice([list(value.values()), list(value), str(value)[:50], 1])
    if isinstance(value, list):
        return rng.choice([dict(enumerate(value)), {"a": value}, len(value), "list"])
    if isinstance(value, bool):
        return rng.choice(["true", 1, [value]])
    if isinstance(value, int | float):
        return rng.choice([str(value), [value], {"value": value}, bool(value)])
    return rng.choice([1.5, [value], {"x": value}, 12345678901234567890])


def _deep(depth: int) -> Any:
    node: Any = 1
    for _ in range(depth):
        node = [node]
    return node


def mutate_once(m: Mutant, rng: random.Random) -> None:
    """One mutation at a random place of ``m.tree``, noted in ``m.done``."""
    places = list(paths(m.tree))
    if not places:
        return
    path = rng.choice(places)
    parent, key = _parent(m.tree, path), path[-1]
    kind = rng.choice(("number", "number", "scale", "raw", "drop", "duplicate", "swap", "deep", "text"))
    value = parent[key]
    if kind == "number":
        parent[key] = rng.choice(NUMBERS)
    elif kind == "scale" and isinstance(value, int | float) and not isinstance(value, bool):
        parent[key] = value * rng.choice((1e300, -1e300, 1e-300, -1, 1e6, 2**60))
    elif kind == "raw":
        name = PLACEHOLDER.format(len(m.raw))
        m.raw[name] = rng.choice(RAW_TEXTS)
        parent[key] = name
    elif kind == "drop" and isinstance(parent, dict):
        del parent[key]
    elif kind == "duplicate" and isinstance(parent, list):
        parent.insert(key, copy.deepcopy(value))
    elif kind == "duplicate" and isinstance(parent, dict):
        parent[f"{key}_"] = copy.deepcopy(value)  # a near-duplicate key (exact ones: the text level)
    elif kind == "deep":
        parent[key] = _deep(rng.choice((3, 8, 33, 100)))  # within the YAML limit and beyond
    elif kind == "text":
        parent[key] = rng.choice(("x" * 5000, "a\nb", "\x00", "é" * 10, "../../etc/passwd", "0x" + "f" * 30))
    else:
        parent[key] = _swap_type(value, rng)
    m.done.append(f"{kind} at {'.'.join(map(str, path))[:80]}")


def mutants(tree: Any, count: int, seed: int, *, most: int = 3) -> Iterator[Mutant]:
    """``count`` mutants of ``tree``, each 1..``most`` mutations, drawn from ``seed``."""
    rng = random.Random(seed)
    for _ in range(count):
        m = Mutant(copy.deepcopy(tree))
        for _ in range(rng.randint(1, most)):
            mutate_once(m, rng)
        yield m


def duplicate_a_key(text: str, rng: random.Random) -> str:
    """A top-level ``key: value`` line of a YAML text given again (PyYAML would keep the last)."""
    lines = [i for i, line in enumerate(text.splitlines()) if line and line[0].isalpha() and ":" in line]
    if not lines:
        return text
    i = rng.choice(lines)
    all_lines = text.splitlines()
    key = all_lines[i].split(":", 1)[0]
    return text + f"{key}: 1\n"


def count(base: int) -> int:
    """``base`` mutations, scaled for a long run."""
    return max(1, round(base * SCALE))
