"""The daemon's configuration: a YAML file, checked completely before the daemon starts.

Everything the per-frame path needs is resolved here, once: file paths (relative to the
configuration file), which DBC messages and signals carry what, where each run-time input of
an effect term comes from and how old it may get. A defect is refused with one line naming
the key (``inputs.temp_c.signal: message IMU_RAWW not in canical.dbc``), so a typo on the
vehicle never shows up as a half-working daemon.
"""

from __future__ import annotations

import math
import os
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from canical.errors import CanicalError
from canical.frames.codec import load_dbc
from canical.yaml_text import parse_yaml

AXES = ("x", "y", "z")
#: Signals of the corrected frame, by role; per-axis names end in the axis letter (RateX...).
RATE_SIGNALS = {"rate": "Rate", "out_of_span": "OutOfSpan", "uncalibrated": "Uncalibrated"}
FRAME_SIGNALS = ("Stale", "CounterGap", "SetTag", "Counter")
STATUS_SIGNALS = ("Page", "State", "FramesIn", "SetId", "Reloads")

_TOP_KEYS = {"bus", "dbc", "sensor", "frames", "axes", "counter", "inputs", "status_period_s", "device",
             "watch_period_s"}


@dataclass(frozen=True)
class InputSource:
    """Where a run-time input of the coefficient sets comes from: a DBC signal, held at its latest value."""

    name: str
    message: str
    signal: str
    max_age_s: float


@dataclass(frozen=True)
class AxisConfig:
    axis: str
    raw_signal: str
    coefficients: Path | None  # None: the axis is sent uncalibrated


@dataclass(frozen=True)
class DeviceSource:
    """The IMU as a CANopen node: at start (and on SIGHUP) its active sets are used, files as fallback."""

    node: int
    timeout_s: float = 1.0


@dataclass(frozen=True)
class DaemonConfig:
    path: Path
    interface: str
    channel: str
    bus_options: dict[str, Any]
    dbc_path: Path
    sensor: str | None
    raw_message: str
    rate_message: str
    status_message: str
    counter_signal: str | None
    axes: tuple[AxisConfig, ...]
    inputs: dict[str, InputSource] = field(default_factory=dict)
    status_period_s: float = 1.0
    watch_period_s: float = 1.0
    device: DeviceSource | None = None

    @property
    def coefficient_paths(self) -> dict[str, Path]:
        return {a.axis: a.coefficients for a in self.axes if a.coefficients is not None}


def load_config(path: str | os.PathLike[str], *, channel: str | None = None) -> DaemonConfig:
    """Read and check a configuration file; ``channel`` overrides ``bus.channel`` (the unit's %i)."""
    cfg_path = Path(path)
    try:
        text = cfg_path.read_text(encoding="utf-8")
    except FileNotFoundError:
        raise CanicalError(f"{cfg_path}: configuration file not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CanicalError(f"{cfg_path}: cannot read configuration ({exc})") from None
    return parse_config(parse_yaml(text, str(cfg_path)), cfg_path, channel=channel)


def parse_config(content: Any, cfg_path: Path, *, channel: str | None = None) -> DaemonConfig:
    """Check parsed content; the DBC it names is loaded to check every message and signal."""

    def fail(key: str, msg: str) -> CanicalError:
        return CanicalError(f"{cfg_path}: {key}: {msg}")

    if not isinstance(content, dict):
        raise CanicalError(f"{cfg_path}: not a canical daemon configuration (expected a mapping)")
    _no_unknown(content, _TOP_KEYS, "", fail)
    base = cfg_path.parent

    bus = _section(content, "bus", fail)
    _no_unknown(bus, {"interface", "channel", "options"}, "bus.", fail)
    interface = _text(bus, "interface", "bus.interface", fail)
    chan = channel or _text(bus, "channel", "bus.channel", fail)
    options = bus.get("options", {}) or {}
    if not isinstance(options, dict):
        raise fail("bus.options", "must be a mapping of python-can keyword arguments")
    for reserved in ("interface", "channel", "can_filters", "bustype"):
        if reserved in options:
            raise fail(f"bus.options.{reserved}", "is set by canical itself")

    dbc_path = _path(content.get("dbc"), base, "dbc", fail, must_exist=True)
    try:
        db = load_dbc(dbc_path)
    except CanicalError as exc:
        raise fail("dbc", str(exc)) from None
    dbc_name = dbc_path.name

    def message(key: str, name: Any) -> Any:
        if not isinstance(name, str) or not name:
            raise fail(key, "must name a DBC message")
        try:
            return db.get_message_by_name(name)
        except KeyError:
            raise fail(key, f"message {name} not in {dbc_name}") from None

    def need_signal(key: str, msg: Any, signal: str) -> None:
        if signal not in {s.name for s in msg.signals}:
            raise fail(key, f"signal {signal} not in message {msg.name} of {dbc_name}")

    frames = content.get("frames", {}) or {}
    if not isinstance(frames, dict):
        raise fail("frames", "must be a mapping")
    _no_unknown(frames, {"raw", "rate", "status"}, "frames.", fail)
    raw_msg = message("frames.raw", frames.get("raw", "IMU_RAW"))
    rate_msg = message("frames.rate", frames.get("rate", "CANICAL_RATE"))
    status_msg = message("frames.status", frames.get("status", "CANICAL_STATUS"))
    if raw_msg.is_multiplexed() or rate_msg.is_multiplexed():
        raise fail("frames", "the raw and rate frames must not be multiplexed")
    if raw_msg.is_fd or rate_msg.is_fd:
        raise fail("frames", "the raw and rate frames must be classic CAN frames")
    if not status_msg.is_multiplexed():
        raise fail("frames.status", f"message {status_msg.name} must be multiplexed by Page")
    for sig in FRAME_SIGNALS:
        need_signal("frames.rate", rate_msg, sig)
    for sig in STATUS_SIGNALS:
        need_signal("frames.status", status_msg, sig)
    if raw_msg.frame_id in (rate_msg.frame_id, status_msg.frame_id):
        raise fail("frames.raw", "must differ from the rate and status frames")

    axes_in = _section(content, "axes", fail)
    _no_unknown(axes_in, set(AXES), "axes.", fail)
    axes = []
    for axis in AXES:
        entry = axes_in.get(axis) or {}
        key = f"axes.{axis}"
        if not isinstance(entry, dict):
            raise fail(key, "must be a mapping (raw, coefficients)")
        _no_unknown(entry, {"raw", "coefficients"}, f"{key}.", fail)
        raw_sig = entry.get("raw", f"GyroRaw{axis.upper()}")
        if not isinstance(raw_sig, str):
            raise fail(f"{key}.raw", "must name a signal of the raw frame")
        need_signal(f"{key}.raw", raw_msg, raw_sig)
        for prefix in RATE_SIGNALS.values():
            need_signal("frames.rate", rate_msg, f"{prefix}{axis.upper()}")
        coeff = entry.get("coefficients")
        coeff_path = None if coeff is None else _path(coeff, base, f"{key}.coefficients", fail)
        axes.append(AxisConfig(axis, raw_sig, coeff_path))
    if not any(a.coefficients for a in axes):
        raise fail("axes", "no axis has a coefficients file")

    counter = content.get("counter", "Counter")
    if counter is not None:
        if not isinstance(counter, str):
            raise fail("counter", "must name a signal of the raw frame, or be null")
        need_signal("counter", raw_msg, counter)

    inputs_in = content.get("inputs", {}) or {}
    if not isinstance(inputs_in, dict):
        raise fail("inputs", "must be a mapping of input name to {signal, max_age_s}")
    inputs: dict[str, InputSource] = {}
    for name, spec in inputs_in.items():
        key = f"inputs.{name}"
        if isinstance(spec, str):
            spec = {"signal": spec}
        if not isinstance(spec, dict):
            raise fail(key, "must be a mapping {signal: MESSAGE.Signal, max_age_s: seconds}")
        _no_unknown(spec, {"signal", "max_age_s"}, f"{key}.", fail)
        ref = spec.get("signal")
        if not isinstance(ref, str) or ref.count(".") != 1:
            raise fail(f"{key}.signal", "must be MESSAGE.Signal")
        msg_name, sig_name = ref.split(".")
        msg = message(f"{key}.signal", msg_name)
        need_signal(f"{key}.signal", msg, sig_name)
        if msg.is_multiplexed():
            raise fail(f"{key}.signal", f"message {msg_name} is multiplexed (not supported for inputs)")
        if msg.frame_id in (rate_msg.frame_id, status_msg.frame_id):
            raise fail(f"{key}.signal", "cannot come from a frame the daemon sends")
        max_age = _positive(spec.get("max_age_s", 1.0), f"{key}.max_age_s", fail)
        inputs[str(name)] = InputSource(str(name), msg_name, sig_name, max_age)

    device = None
    device_in = content.get("device")
    if device_in is not None:
        if not isinstance(device_in, dict):
            raise fail("device", "must be a mapping {node: CANopen node id, timeout_s: seconds}")
        _no_unknown(device_in, {"node", "timeout_s"}, "device.", fail)
        node = device_in.get("node")
        if not isinstance(node, int) or isinstance(node, bool) or not 1 <= node <= 127:
            raise fail("device.node", f"must be a CANopen node id 1..127, got {node!r}")
        device = DeviceSource(node, _positive(device_in.get("timeout_s", 1.0), "device.timeout_s", fail))

    return DaemonConfig(
        path=cfg_path,
        interface=interface,
        channel=chan,
        bus_options=dict(options),
        dbc_path=dbc_path,
        sensor=_optional_text(content, "sensor", fail),
        raw_message=raw_msg.name,
        rate_message=rate_msg.name,
        status_message=status_msg.name,
        counter_signal=counter,
        axes=tuple(axes),
        inputs=inputs,
        status_period_s=_positive(content.get("status_period_s", 1.0), "status_period_s", fail),
        watch_period_s=_positive(content.get("watch_period_s", 1.0), "watch_period_s", fail),
        device=device,
    )


def _no_unknown(section: Mapping[str, Any], allowed: set[str], prefix: str, fail) -> None:
    for key in section:
        if key not in allowed:
            raise fail(f"{prefix}{key}", f"unknown key (expected one of {', '.join(sorted(allowed))})")


def _section(content: dict, key: str, fail) -> dict:
    value = content.get(key)
    if not isinstance(value, dict):
        raise fail(key, "missing or not a mapping")
    return value


def _text(section: dict, key: str, name: str, fail) -> str:
    value = section.get(key)
    if not isinstance(value, str) or not value:
        raise fail(name, "missing or not a non-empty string")
    return value


def _optional_text(content: dict, key: str, fail) -> str | None:
    value = content.get(key)
    if value is None:
        return None
    if not isinstance(value, str | int) or isinstance(value, bool) or value == "":
        raise fail(key, "must be a non-empty string")
    return str(value)


def _positive(value: Any, key: str, fail) -> float:
    number = isinstance(value, int | float) and not isinstance(value, bool)
    if not number or not math.isfinite(value) or value <= 0:
        raise fail(key, f"must be a positive number of seconds, got {value!r}")
    return float(value)


def _path(value: Any, base: Path, key: str, fail, *, must_exist: bool = False) -> Path:
    if not isinstance(value, str) or not value:
        raise fail(key, "missing or not a file path")
    path = Path(value)
    if not path.is_absolute():
        path = base / path
    if must_exist and not path.is_file():
        raise fail(key, f"file {path} not found")
    return path
