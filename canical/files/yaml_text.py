"""Parse YAML written by people: every defect becomes one line naming the file (and line).

Why limits: a set or a configuration is read by a daemon that must not stall, crash or guess.
A YAML file can hold what no set or configuration needs and what breaks a reader later: an
alias bomb (a few lines whose aliases expand to millions of values: one refusal echoed a
3.5-million-character line), a 5,000-digit integer (Python refuses to convert it, with a
traceback), nesting 1,000 deep (a ``RecursionError`` in whoever walks it), a key given twice
(PyYAML keeps the last without a word). All are refused here, before any arithmetic, in one line
of bounded length; what passes is plain data within :data:`MAX_VALUES` values and
:data:`MAX_DEPTH` levels, every integer within :data:`MAX_INT_DIGITS` digits.
"""

from __future__ import annotations

from typing import Any

import yaml

from canical.errors import CanicalError

#: libyaml's parser where PyYAML was built with it (values are still built by PyYAML's safe
#: constructor, so the content is the same): the pure-Python parser is most of the time a
#: daemon's reload takes, tens of milliseconds per coefficient file on a slow machine.
BASE_LOADER: type[yaml.SafeLoader] = getattr(yaml, "CSafeLoader", yaml.SafeLoader)
#: The largest text read: a set with splines is a few kilobytes, a configuration less.
MAX_BYTES = 4 * 1024 * 1024
#: Values in a document, counting each alias's target as often as it is used (a set with
#: splines holds a few thousand).
MAX_VALUES = 100_000
#: Levels of nesting: a set's deepest is four.
MAX_DEPTH = 32
#: Digits of an integer: a CAN id or a count has at most 20 (2**64).
MAX_INT_DIGITS = 20


class _Refused(Exception):
    """A limit of this module, with its line when known (caught in :func:`parse_yaml`)."""

    def __init__(self, what: str, mark: Any = None) -> None:
        super().__init__(what)
        self.mark = mark


class LOADER(BASE_LOADER):  # type: ignore[valid-type,misc]
    """The safe loader, refusing a key given twice in one mapping (PyYAML keeps the last)."""

    def construct_mapping(self, node: yaml.MappingNode, deep: bool = False) -> dict[Any, Any]:
        seen: set[Any] = set()
        for key_node, _ in node.value:
            if key_node.tag == "tag:yaml.org,2002:merge":  # "<<: *anchor": merged, not a key
                continue
            key = self.construct_object(key_node, deep=True)
            try:
                duplicate = key in seen
            except TypeError:  # an unhashable key: the safe constructor says so
                break
            if duplicate:
                raise _Refused(f"key {_short(key)} given twice", key_node.start_mark)
            seen.add(key)
        return super().construct_mapping(node, deep=deep)


def parse_yaml(text: str, source: str) -> Any:
    """The document's content, or a :class:`CanicalError` saying in one line what is wrong where."""
    if len(text) > MAX_BYTES:
        raise CanicalError(f"{source}: larger than {MAX_BYTES // (1024 * 1024)} MiB: not a canical file")
    try:
        content = yaml.load(text, Loader=LOADER)  # a safe loader: plain data only
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        raise CanicalError(f"{source}: not valid YAML{_at(mark)}") from None
    except _Refused as exc:
        raise CanicalError(f"{source}: {exc}{_at(exc.mark)}") from None
    except (ValueError, OverflowError):  # an integer Python will not convert (over 4,300 digits)
        raise CanicalError(f"{source}: a number with more than {MAX_INT_DIGITS} digits") from None
    except RecursionError:
        raise CanicalError(f"{source}: nested deeper than {MAX_DEPTH} levels") from None
    try:
        _check_bounds(content)
    except _Refused as exc:
        raise CanicalError(f"{source}: {exc}") from None
    return content


def _check_bounds(content: Any) -> None:
    """Walk the document once, within the limits (an alias's target counted at every use)."""
    budget = MAX_VALUES
    stack: list[tuple[Any, int]] = [(content, 0)]
    while stack:
        value, depth = stack.pop()
        budget -= 1
        if budget < 0:
            raise _Refused(f"more than {MAX_VALUES:,} values (aliases that expand without end?)")
        if depth > MAX_DEPTH:
            raise _Refused(f"nested deeper than {MAX_DEPTH} levels")
        if isinstance(value, bool):
            continue
        if isinstance(value, int) and len(str(abs(value))) > MAX_INT_DIGITS:
            raise _Refused(f"a number with more than {MAX_INT_DIGITS} digits")
        if isinstance(value, dict):
            stack.extend((item, depth + 1) for pair in value.items() for item in pair)
        elif isinstance(value, list):
            stack.extend((item, depth + 1) for item in value)


def _at(mark: Any) -> str:
    return f" at line {mark.line + 1}" if mark is not None else ""


def _short(value: Any, limit: int = 40) -> str:
    """A user's value in a message: its repr, cut to ``limit`` characters, on one line."""
    text = repr(value)
    return text if len(text) <= limit else text[: limit - 1] + "…"
