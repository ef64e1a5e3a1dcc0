"""The learned bias kept across restarts: one small JSON file, written atomically, keyed by the set.

Why keyed by the set's id: what was learned is a correction on top of one set's output; under
another set (a new calibration, another sensor) it means nothing and must not be used. Why a
CRC: a file that was damaged (a disk fault, a hand edit) must be refused, not half-used. A
missing, damaged or foreign file is never an error that stops the daemon: the tracker starts
afresh and the reason is one line for the log. Writes go through :mod:`canical.files.atomic_file`,
so a process killed mid-write leaves the old file or the new, never a mix.
"""

from __future__ import annotations

import json
import math
import os
import zlib
from dataclasses import dataclass
from typing import Any

from canical.files.atomic_file import write_text_atomic
from canical.tracking.estimate import AxisBias

FORMAT = "canical-bias-state"
VERSION = 1
FIELDS = ("b0", "slope", "p00", "p01", "p11")


@dataclass(frozen=True)
class LoadedState:
    """What a state file gave: the learned states to start from (None: start afresh) and why."""

    learned: tuple[AxisBias, ...] | None
    note: str


def _crc(body: dict[str, Any]) -> int:
    return zlib.crc32(json.dumps(body, sort_keys=True, separators=(",", ":")).encode()) & 0xFFFFFFFF


def dumps(set_id: int, axes: tuple[str, ...], learned: list[AxisBias] | tuple[AxisBias, ...]) -> str:
    """The file's text: the set's id, the axes, each axis's state, and a CRC over them."""
    body: dict[str, Any] = {
        "format": FORMAT,
        "version": VERSION,
        "set_id": f"0x{set_id:08x}",
        "axes": list(axes),
        "states": [{**{f: getattr(s, f) for f in FIELDS}, "updates": s.updates} for s in learned],
    }
    return json.dumps({**body, "crc32": f"0x{_crc(body):08x}"}, indent=1) + "\n"


def save(path: str | os.PathLike[str], set_id: int, axes: tuple[str, ...],
         learned: list[AxisBias] | tuple[AxisBias, ...]) -> None:
    write_text_atomic(path, dumps(set_id, axes, learned))


def load(path: str | os.PathLike[str], set_id: int, axes: tuple[str, ...]) -> LoadedState:
    """The learned states in ``path`` if they are whole and for this set and axes; else afresh, why."""
    name = str(path)
    try:
        with open(path, encoding="utf-8") as handle:
            text = handle.read()
    except FileNotFoundError:
        return LoadedState(None, f"bias state {name}: none yet, learning afresh")
    except (OSError, UnicodeDecodeError) as exc:
        return LoadedState(None, f"bias state {name}: cannot read ({exc}), learning afresh")
    try:
        learned = parse(text, set_id, axes)
    except ValueError as exc:
        return LoadedState(None, f"bias state {name}: {exc}, learning afresh")
    updates = sum(s.updates for s in learned)
    return LoadedState(learned, f"bias state {name}: {updates} window updates for set 0x{set_id:08x} loaded")


def parse(text: str, set_id: int, axes: tuple[str, ...]) -> tuple[AxisBias, ...]:
    """Check everything; any defect is one ValueError line saying what."""
    try:
        content = json.loads(text)
    except ValueError:
        raise ValueError("damaged (not JSON)") from None
    if not isinstance(content, dict) or content.get("format") != FORMAT:
        raise ValueError("not a canical bias state file")
    if content.get("version") != VERSION:
        raise ValueError(f"version {content.get('version')!r} not supported (this canical reads {VERSION})")
    body = {k: v for k, v in content.items() if k != "crc32"}
    if content.get("crc32") != f"0x{_crc(body):08x}":
        raise ValueError("damaged (CRC mismatch)")
    if content.get("set_id") != f"0x{set_id:08x}":
        raise ValueError(f"learned for set {content.get('set_id')}, not this set 0x{set_id:08x}")
    if content.get("axes") != list(axes):
        raise ValueError(f"learned for axes {content.get('axes')}, not {list(axes)}")
    states = content.get("states")
    if not isinstance(states, list) or len(states) != len(axes):
        raise ValueError("states missing or not one per axis")
    return tuple(_state(s, i) for i, s in enumerate(states))


def _state(raw: Any, i: int) -> AxisBias:
    if not isinstance(raw, dict):
        raise ValueError(f"states[{i}] is not a mapping")
    values = {}
    for f in FIELDS:
        v = raw.get(f)
        if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
            raise ValueError(f"states[{i}].{f} is not a finite number")
        values[f] = float(v)
    p00, p01, p11 = values["p00"], values["p01"], values["p11"]
    if p00 < 0 or p11 < 0 or p01 * p01 > p00 * p11 * (1 + 1e-9):
        raise ValueError(f"states[{i}] covariance is not a covariance")
    updates = raw.get("updates")
    if isinstance(updates, bool) or not isinstance(updates, int) or updates < 0:
        raise ValueError(f"states[{i}].updates is not a count")
    return AxisBias(updates=updates, **values)
