"""The daemon's ``bias_tracking:`` section, checked key by key before the daemon starts.

Why here and not in the daemon's configuration module: the keys are the tracker's settings and
their checks are the tracker's (:class:`~canical.tracking.config.TrackerConfig`), so they live
beside it; the daemon's configuration calls :func:`parse_bias_tracking` with its own ``fail``
(which names the file) and then checks that the cue and the temperature name inputs of its
``inputs:`` section (a DBC signal held at its latest value, as every input), which only it can.
Time since power-on is the ``time_s`` input where there is one. :data:`KEYS` documents every key
for the configuration reference.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from canical.errors import CanicalError
from canical.tracking.config import TrackerConfig

Fail = Callable[[str, str], CanicalError]
PREFIX = "bias_tracking."
DEFAULT = TrackerConfig()


@dataclass(frozen=True)
class Key:
    key: str
    default: str
    check: str
    meaning: str


#: Every key of the section: what the reference page lists and what the parser accepts.
KEYS: tuple[Key, ...] = (
    Key("enabled", "false", "true or false", "learn each axis's bias at standstills and subtract it"),
    Key("arw_deg_rt_h", f"each set's fit.arw_deg_rt_h, else {DEFAULT.arw_deg_rt_h:g}", "positive number",
        "the sensor's angle random walk (deg/√h); given here, it overrides what calibrate measured"),
    Key("window_s", f"{DEFAULT.window_s:g}", "positive number",
        "statistics window: decisions once per window"),
    Key("vibration_dps", f"{DEFAULT.vibration_dps:g}", "number ≥ 0",
        "sample spread allowed at a standstill beyond the white noise (engine idle vibration, rms)"),
    Key("bound_dps", f"{DEFAULT.bound_dps:g}", "positive number",
        "plausibility bound: a mean beyond it is refused (a turn, not a bias)"),
    Key("slew_dps_per_s", f"{DEFAULT.slew_dps_per_s:g}", "positive number",
        "fastest change of the applied bias: no step in the output"),
    Key("turn_on_sigma_dps", f"{DEFAULT.turn_on_sigma_dps:g}", "positive number",
        "turn-on repeatability: how far a new power-on's bias may be from the last"),
    Key("temperature", "temp_c", "an input's name", "the input the bias is learned against"),
    Key("cue", "none", "a mapping", "an input that says whether the vehicle moves (speed, a flag)"),
    Key("cue.input", "required", "an input's name", "e.g. `speed`, mapped in `inputs:` to a DBC signal"),
    Key("cue.below", "0.1", "positive number",
        "the vehicle stands while the input is within ± this (a signed speed in reverse is moving)"),
    Key("state_file", "none", "file path", "where the learned bias is kept across restarts (atomically)"),
)
_NUMBERS = ("arw_deg_rt_h", "window_s", "vibration_dps", "bound_dps", "slew_dps_per_s", "turn_on_sigma_dps")


@dataclass(frozen=True)
class BiasTrackingSettings:
    """The section, checked: whether to track, the tracker's settings, the cue's signal, the state file."""

    enabled: bool
    tracker: TrackerConfig
    cue_input: str | None  # the name of an input
    temperature_input: str
    state_file: str | None  # as written: the daemon resolves it against its configuration's folder
    arw_given: bool = False  # arw_deg_rt_h was given: it overrides each set's own


def parse_bias_tracking(section: Any, fail: Fail) -> BiasTrackingSettings:
    """Check the section (None: off); any defect is ``fail(key, message)`` naming the key."""
    if section is None:
        return BiasTrackingSettings(False, DEFAULT, None, "temp_c", None)
    if not isinstance(section, dict):
        raise fail("bias_tracking", "must be a mapping")
    top = {k.key for k in KEYS if "." not in k.key}
    for key in section:
        if key not in top:
            raise fail(f"{PREFIX}{key}", f"unknown key (expected one of {', '.join(sorted(top))})")
    enabled = section.get("enabled", False)
    if not isinstance(enabled, bool):
        raise fail(f"{PREFIX}enabled", f"must be true or false, got {enabled!r}")
    values: dict[str, Any] = {name: _number(section[name], f"{PREFIX}{name}", fail)
                              for name in _NUMBERS if name in section}
    cue_input, below = _cue(section.get("cue"), fail)
    temperature = section.get("temperature", "temp_c")
    if not isinstance(temperature, str) or not temperature:
        raise fail(f"{PREFIX}temperature", "must name an input")
    state = section.get("state_file")
    if state is not None and (not isinstance(state, str) or not state):
        raise fail(f"{PREFIX}state_file", "must be a file path")
    try:
        tracker = dataclasses.replace(DEFAULT, cue_threshold=below, **values)
    except ValueError as exc:
        name = str(exc).split(" ", 1)[0]
        raise fail(f"{PREFIX}{name}", str(exc).split(" ", 1)[1]) from None
    return BiasTrackingSettings(enabled, tracker, cue_input, temperature, state,
                                arw_given="arw_deg_rt_h" in section)


def _number(value: Any, key: str, fail: Fail) -> float:
    if isinstance(value, bool) or not isinstance(value, int | float) or not math.isfinite(value):
        raise fail(key, f"must be a finite number, got {value!r}")
    return float(value)


def _cue(cue: Any, fail: Fail) -> tuple[str | None, float | None]:
    if cue is None:
        return None, None
    if not isinstance(cue, dict):
        raise fail(f"{PREFIX}cue", "must be a mapping with input (an input's name) and below")
    for key in cue:
        if key not in ("input", "below"):
            raise fail(f"{PREFIX}cue.{key}", "unknown key (expected one of below, input)")
    name = cue.get("input")
    if not isinstance(name, str) or not name:
        raise fail(f"{PREFIX}cue.input", f"must name an input, got {name!r}")
    below = _number(cue.get("below", 0.1), f"{PREFIX}cue.below", fail)
    if below <= 0.0:  # the vehicle stands while the cue is within ± below: none would
        raise fail(f"{PREFIX}cue.below", f"must be a positive number, got {below!r}")
    return name, below
