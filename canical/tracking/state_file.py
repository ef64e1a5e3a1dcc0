"""The learned bias kept across restarts: one small JSON file, written atomically, keyed by the set.

Why keyed by the set's id: what was learned is a correction on top of one set's output; under
another set (a new calibration, another sensor) it means nothing and must not be used. Why a
CRC: a file that was damaged (a disk fault, a hand edit) must be refused, not half-used. A
missing, damaged or foreign file is never an error that stops the daemon: the tracker starts
afresh and the reason is one line for the log. Writes go through :mod:`canical.files.atomic_file`,
so a process killed mid-write leaves the old file or the new, never a mix.

Why bounds beyond the CRC: a CRC tells damage, not sense. A file with a valid CRC and a bias of
100 deg/s was applied to every frame; a slope of -1e308 crashed the daemon at its first status
frame. Everything loaded is held to the tracker's own limits (:class:`StateLimits`) before use:
the bias within the plausibility bound the tracker refuses windows beyond, the slope within 5σ
of its prior, variances no larger than the priors they start from; the file is read to at most
:data:`MAX_BYTES` and a number or nesting JSON cannot hold as a float is refused in one line.
"""

from __future__ import annotations

import json
import math
import os
import zlib
from dataclasses import dataclass
from typing import Any

from canical.errors import one_line
from canical.files.atomic_file import write_text_atomic
from canical.tracking.config import TrackerConfig
from canical.tracking.estimate import AxisBias

FORMAT = "canical-bias-state"
VERSION = 1
FIELDS = ("b0", "slope", "p00", "p01", "p11")
#: A state file holds a few axes of five numbers: far below this. More is not a state file.
MAX_BYTES = 64 * 1024
#: The slope may be this many prior standard deviations from zero (the prior's reach).
SLOPE_SIGMAS = 5.0
#: The offset's variance may grow past its prior by wandering between stops: up to this factor.
P00_GROWTH = 4.0
#: ``updates`` counts windows; more than this is not a count a vehicle reaches (2**53: a float's).
MAX_UPDATES = 2**53


@dataclass(frozen=True)
class StateLimits:
    """What a loaded state may hold: the tracker's own bounds and priors."""

    bias_dps: float
    slope_dps_per_c: float
    p00: float
    p11: float

    @classmethod
    def of(cls, config: TrackerConfig) -> StateLimits:
        prior00 = max(config.turn_on_sigma_dps, config.bound_dps) ** 2
        return cls(bias_dps=config.bound_dps, slope_dps_per_c=SLOPE_SIGMAS * config.temp_slope_sigma,
                   p00=P00_GROWTH * prior00, p11=config.temp_slope_sigma**2 * (1 + 1e-9))


@dataclass(frozen=True)
class LoadedState:
    """What a state file gave: the learned states to start from (None: start afresh) and why."""

    learned: tuple[AxisBias, ...] | None
    note: str
    refused: bool = False  # the file was there but not used: damaged, implausible or foreign


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


def load(path: str | os.PathLike[str], set_id: int, axes: tuple[str, ...],
         limits: StateLimits) -> LoadedState:
    """The learned states in ``path`` if they are whole, plausible and for this set and axes; else
    afresh, and why (``damaged`` True when the file exists but was refused: worth a warning)."""
    name = str(path)
    try:
        with open(path, encoding="utf-8") as handle:
            text = handle.read(MAX_BYTES + 1)
    except FileNotFoundError:
        return LoadedState(None, f"bias state {name}: none yet, learning afresh")
    except (OSError, UnicodeDecodeError) as exc:
        return LoadedState(None, f"bias state {name}: cannot read ({exc}), learning afresh", refused=True)
    try:
        learned = parse(text, set_id, axes, limits)
    except ValueError as exc:
        return LoadedState(None, f"bias state {name}: {exc}, learning afresh", refused=True)
    updates = sum(s.updates for s in learned)
    return LoadedState(learned, f"bias state {name}: {updates} window updates for set 0x{set_id:08x} loaded")


def parse(text: str, set_id: int, axes: tuple[str, ...], limits: StateLimits) -> tuple[AxisBias, ...]:
    """Check everything; any defect is one ValueError line saying what."""
    if len(text) > MAX_BYTES:
        raise ValueError(f"larger than {MAX_BYTES // 1024} KiB: not a bias state file")
    try:
        content = json.loads(text, object_pairs_hook=_unique_keys)
    except _DuplicateKey as exc:
        raise ValueError(str(exc)) from None
    except (ValueError, RecursionError):  # RecursionError: nesting deeper than the parser's stack
        raise ValueError("damaged (not JSON)") from None
    if not isinstance(content, dict) or content.get("format") != FORMAT:
        raise ValueError("not a canical bias state file")
    if content.get("version") != VERSION:
        raise ValueError(f"version {_short(content.get('version'))} not supported "
                         f"(this canical reads {VERSION})")
    body = {k: v for k, v in content.items() if k != "crc32"}
    if content.get("crc32") != f"0x{_crc(body):08x}":
        raise ValueError("damaged (CRC mismatch)")
    if content.get("set_id") != f"0x{set_id:08x}":
        raise ValueError(f"learned for set {_short(content.get('set_id'))}, not this set 0x{set_id:08x}")
    if content.get("axes") != list(axes):
        raise ValueError(f"learned for axes {_short(content.get('axes'))}, not {list(axes)}")
    states = content.get("states")
    if not isinstance(states, list) or len(states) != len(axes):
        raise ValueError("states missing or not one per axis")
    return tuple(_state(s, i, limits) for i, s in enumerate(states))


class _DuplicateKey(ValueError):
    """A key given twice in one object."""


def _unique_keys(pairs: list[tuple[str, Any]]) -> dict[str, Any]:
    """An object's keys, each once. Why: json keeps a duplicate's last value without a word, so a
    hand-edited file could say one thing to a reader and another to canical (as YAML is refused)."""
    content: dict[str, Any] = {}
    for key, value in pairs:
        if key in content:
            raise _DuplicateKey(f"key {_short(key)} given twice")
        content[key] = value
    return content


def _short(value: Any) -> str:
    """A value from the file as a log line may echo it: one line, at most 40 characters (a file's
    set id of 5,000 characters or nested 100 deep made a note of as many)."""
    return one_line(repr(value), 40)


def _number(raw: dict[str, Any], key: str, i: int) -> float:
    v = raw.get(key)
    if isinstance(v, bool) or not isinstance(v, int | float):
        raise ValueError(f"states[{i}].{key} is not a finite number")
    try:
        value = float(v)  # an int too large for a float raises here, before any arithmetic
    except OverflowError:
        raise ValueError(f"states[{i}].{key} is not a finite number") from None
    if not math.isfinite(value):
        raise ValueError(f"states[{i}].{key} is not a finite number")
    return value


def _state(raw: Any, i: int, limits: StateLimits) -> AxisBias:
    if not isinstance(raw, dict):
        raise ValueError(f"states[{i}] is not a mapping")
    values = {f: _number(raw, f, i) for f in FIELDS}
    p00, p01, p11 = values["p00"], values["p01"], values["p11"]
    if p00 < 0 or p11 < 0 or p01 * p01 > p00 * p11 * (1 + 1e-9):
        raise ValueError(f"states[{i}] covariance is not a covariance")
    _within(values["b0"], limits.bias_dps, f"states[{i}].b0", "deg/s, the plausibility bound")
    _within(values["slope"], limits.slope_dps_per_c, f"states[{i}].slope", "deg/s/°C, 5σ of its prior")
    _within(p00, limits.p00, f"states[{i}].p00", "(deg/s)², the offset's prior variance")
    _within(p11, limits.p11, f"states[{i}].p11", "(deg/s/°C)², the slope's prior variance")
    updates = raw.get("updates")
    if isinstance(updates, bool) or not isinstance(updates, int) or not 0 <= updates <= MAX_UPDATES:
        raise ValueError(f"states[{i}].updates is not a count")
    return AxisBias(updates=updates, **values)


def _within(value: float, limit: float, where: str, what: str) -> None:
    if abs(value) > limit:
        raise ValueError(f"{where} {value:.4g} is beyond ±{limit:.4g} {what}: implausible")
