"""Parse YAML written by people: a syntax error becomes one line naming the file and line."""

from __future__ import annotations

from typing import Any

import yaml

from canical.errors import CanicalError

#: libyaml's parser where PyYAML was built with it (values are still built by PyYAML's safe
#: constructor, so the content is the same): the pure-Python parser is most of the time a
#: daemon's reload takes, tens of milliseconds per coefficient file on a slow machine.
LOADER = getattr(yaml, "CSafeLoader", yaml.SafeLoader)


def parse_yaml(text: str, source: str) -> Any:
    """The document's content, or a :class:`CanicalError` saying where the YAML is broken."""
    try:
        return yaml.load(text, Loader=LOADER)  # a safe loader: plain data only
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark else ""
        raise CanicalError(f"{source}: not valid YAML{where}") from None
