"""Parse YAML written by people: a syntax error becomes one line naming the file and line."""

from __future__ import annotations

from typing import Any

import yaml

from canical.errors import CanicalError


def parse_yaml(text: str, source: str) -> Any:
    """The document's content, or a :class:`CanicalError` saying where the YAML is broken."""
    try:
        return yaml.safe_load(text)
    except yaml.YAMLError as exc:
        mark = getattr(exc, "problem_mark", None)
        where = f" at line {mark.line + 1}" if mark else ""
        raise CanicalError(f"{source}: not valid YAML{where}") from None
