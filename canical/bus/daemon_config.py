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
import re
from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from cantools.database.can import Database, Message

from canical.errors import CanicalError, one_line
from canical.files.key_file import read_public
from canical.files.yaml_text import parse_yaml
from canical.frames.codec import load_dbc
from canical.frames.dbc_files import ALL_EXTENDED, DbcSet, dbc_label, require_sound, undecoded_reason
from canical.frames.frame_match import J1939Source, frame_match, parse_j1939_source
from canical.sessions.canlog_format import HELD_AXIS_PREFIX
from canical.sets.signing import TrustedKey
from canical.tracking.settings import BiasTrackingSettings, parse_bias_tracking

AXES = ("x", "y", "z")
#: Signals of the corrected frame, by role; per-axis names end in the axis letter (RateX...).
RATE_SIGNALS = {"rate": "Rate", "out_of_span": "OutOfSpan", "uncalibrated": "Uncalibrated"}
FRAME_SIGNALS = ("Stale", "CounterGap", "SetTag", "Counter")
STATUS_SIGNALS = ("Page", "State", "FramesIn", "SetId", "Reloads")

_TOP_KEYS = {"bus", "dbc", "sensor", "frames", "axes", "counter", "inputs", "status_period_s", "device",
             "watch_period_s", "own_layout", "bias_tracking", "j1939", "imu_set", "trust",
             "field_log"}


@dataclass(frozen=True)
class InputSource:
    """Where a run-time input of the coefficient sets comes from: a DBC signal, held at its latest value."""

    name: str
    message: str
    signal: str
    max_age_s: float


HELD_AXIS_MAX_AGE_S = 0.1


@dataclass(frozen=True)
class AxisConfig:
    axis: str
    #: None: the axis is absent (left out of ``axes:``, as on a single-axis yaw-rate sensor):
    #: nothing is read for it, and it goes out uncalibrated.
    raw_signal: str | None
    coefficients: Path | None  # None: the axis is sent uncalibrated
    raw_units: str = ""  # the raw signal's unit as its DBC gives it ("": none given)
    #: The message the raw signal is in, when not the raw frame: its latest value is held (an
    #: input named ``held``) and corrected with the raw frame's axes when the raw frame comes.
    message: str | None = None
    max_age_s: float = HELD_AXIS_MAX_AGE_S

    @property
    def present(self) -> bool:
        """The axis is named in ``axes:`` (read and, with a set, corrected)."""
        return self.raw_signal is not None

    @property
    def held(self) -> str | None:
        """The input name its latest raw value is held under (None: in the raw frame itself)."""
        return None if self.message is None else HELD_AXIS_PREFIX + self.axis


@dataclass(frozen=True)
class DeviceSource:
    """The IMU as a CANopen node: at start (and on SIGHUP) its active sets are used, files as fallback."""

    node: int
    timeout_s: float = 1.0


@dataclass(frozen=True)
class OwnLayoutOutput:
    """The corrected frame in the IMU's own layout: the raw frame's message re-encoded with the
    axes' corrected values, sent at ``frame_id`` on ``channel`` (None: the sensor's own bus;
    another channel: a one-way gateway, nothing is read from it)."""

    frame_id: int
    extended: bool
    channel: str | None
    #: Axes from several messages: each other message's id (name, id, extended), in the raw
    #: frame's layout's place re-encoded from its latest frame when the raw frame comes.
    held_ids: tuple[tuple[str, int, bool], ...] = ()


@dataclass(frozen=True)
class BiasTracking:
    """``bias_tracking:`` resolved against the inputs: None where the daemon has no such input."""

    settings: BiasTrackingSettings
    temperature_input: str | None
    time_input: str | None  # time since power-on (else frame time since the first raw frame)
    state_file: Path | None


@dataclass(frozen=True)
class FieldLogConfig:
    """``field_log:``: where the tracker's decisions are kept as segments for the fleet, the bound on
    their size, and the vehicle they are from (:mod:`canical.fieldlog`)."""

    directory: Path
    max_bytes: int
    vehicle_id: str


#: ``field_log.max_mb``'s default: a year of a vehicle's standstills is a few megabytes.
FIELD_LOG_MAX_MB = 64.0
_VEHICLE_ID = re.compile(r"^[A-Za-z0-9][A-Za-z0-9._-]{0,63}$")


@dataclass(frozen=True)
class Trust:
    """``trust:``: the public keys a set must be signed by (the calibration lab's).

    ``require`` (the default) refuses, as a corrupt set is refused, a set no trusted key signed for
    its sensor, or one older than the set it would replace; false checks and warns but adopts
    (while a fleet's sets are being signed)."""

    keys: tuple[TrustedKey, ...]
    require: bool = True


@dataclass(frozen=True)
class DaemonConfig:
    path: Path
    interface: str
    channel: str
    bus_options: dict[str, Any]
    dbc_path: DbcSet  # the configuration's DBC files (canical's own frames are loaded beside them)
    sensor: str | None
    raw_message: str
    rate_message: str | None  # None: CANICAL_RATE not sent (frames.rate: null, own_layout instead)
    status_message: str | None  # None: CANICAL_STATUS not sent (frames.status: null)
    counter_signal: str | None
    axes: tuple[AxisConfig, ...]
    inputs: dict[str, InputSource] = field(default_factory=dict)
    status_period_s: float = 1.0
    watch_period_s: float = 1.0
    device: DeviceSource | None = None
    own_layout: OwnLayoutOutput | None = None
    bias_tracking: BiasTracking | None = None  # None: not enabled
    j1939_source: J1939Source = None  # J1939 messages matched by PGN and this source (None: the DBC's)
    imu_set: Path | None = None  # one IMU set for the three axes and their coupling (not per-axis files)
    trust: Trust | None = None  # None: sets are not authenticated (one warning at start)
    field_log: FieldLogConfig | None = None  # None: no field log


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


Fail = Callable[[str, str], CanicalError]
#: A section of the YAML file as read: keys to whatever the file holds (checked where used).
Json = dict[str, Any]


class _Dbc:
    """The DBC a configuration names, and its checks: each defect one line naming the key."""

    def __init__(self, db: Database, name: str, fail: Fail) -> None:
        self.db, self.name, self.fail = db, name, fail

    def message(self, key: str, name: Any) -> Message:
        if not isinstance(name, str) or not name:
            raise self.fail(key, "must name a DBC message")
        try:
            message = self.db.get_message_by_name(name)
        except KeyError:
            raise self.fail(key, f"message {name} not in {self.name}") from None
        try:
            require_sound(message, self.name)
        except CanicalError as exc:
            raise self.fail(key, str(exc)) from None
        return message

    def need_signal(self, key: str, msg: Message, signal: str) -> None:
        if signal not in {s.name for s in msg.signals}:
            why = undecoded_reason(msg.name, signal)
            raise self.fail(key, why or f"signal {signal} not in message {msg.name} of {self.name}")


@dataclass(frozen=True)
class _Frames:
    """The frames the daemon reads (raw) and sends (rate, status)."""

    raw: Message
    rate: Message | None  # None: not sent
    status: Message | None  # None: not sent


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
    options = _bus_options(bus, fail)
    dbc_path = DbcSet(_dbc_files(content.get("dbc"), base, fail), j1939=_j1939_messages(content, fail))
    try:
        dbc = _Dbc(load_dbc(dbc_path), dbc_label(dbc_path), fail)
    except CanicalError as exc:
        raise fail("dbc", str(exc)) from None
    frames = _frames(content, dbc)
    imu_set = _imu_set(content, base, fail)
    axes = _axes(content, frames, dbc, base, imu_set=imu_set is not None)
    _one_axis_per_signal(axes, dbc.fail)
    counter = _counter(content, frames, dbc)
    inputs = _inputs(content, frames, dbc)
    inputs.update({a.held: InputSource(a.held, a.message, a.raw_signal, a.max_age_s)
                   for a in axes
                   if a.held is not None and a.message is not None and a.raw_signal is not None})
    device = _device(content, fail)
    j1939 = _j1939_source(content, fail)
    _raw_frames_can_match(frames, axes, dbc, j1939)
    own_layout = _own_layout_output(content, frames, inputs, dbc, chan, j1939)
    tracking = _bias_tracking(content, inputs, base, fail)
    return DaemonConfig(
        path=cfg_path,
        interface=interface,
        channel=chan,
        bus_options=options,
        dbc_path=dbc_path,
        sensor=_optional_text(content, "sensor", fail),
        raw_message=frames.raw.name,
        rate_message=None if frames.rate is None else frames.rate.name,
        status_message=None if frames.status is None else frames.status.name,
        counter_signal=counter,
        axes=axes,
        inputs=inputs,
        status_period_s=_positive(content.get("status_period_s", 1.0), "status_period_s", fail),
        watch_period_s=_positive(content.get("watch_period_s", 1.0), "watch_period_s", fail),
        device=device,
        own_layout=own_layout,
        bias_tracking=tracking,
        j1939_source=j1939,
        imu_set=imu_set,
        trust=_trust(content, base, fail),
        field_log=_field_log(content, tracking, base, fail),
    )


def _field_log(content: Json, tracking: BiasTracking | None, base: Path, fail: Fail) -> FieldLogConfig | None:
    """``field_log``: a folder, a size bound in MB and the vehicle's id; only with bias tracking on
    (its records are the tracker's decisions)."""
    section = _optional_section(content, "field_log", {"dir", "max_mb", "vehicle_id"},
                                "{dir: FOLDER, max_mb: 64, vehicle_id: ID}", fail)
    if section is None:
        return None
    directory = _path(section.get("dir"), base, "field_log.dir", fail)
    max_mb = section.get("max_mb", FIELD_LOG_MAX_MB)
    if isinstance(max_mb, bool) or not isinstance(max_mb, int | float) or not 0.1 <= max_mb <= 1e6:
        raise fail("field_log.max_mb", f"must be a number of megabytes from 0.1 to 1000000, got {max_mb!r}")
    vehicle = section.get("vehicle_id")
    if not isinstance(vehicle, str) or not _VEHICLE_ID.match(vehicle):
        raise fail("field_log.vehicle_id", "must be the vehicle's id: 1-64 letters, digits, '.', '_' or '-', "
                   f"got {one_line(repr(vehicle), 80)}")
    if tracking is None:
        raise fail("field_log", "needs bias_tracking: {enabled: true} "
                   "(its records are the tracker's decisions)")
    return FieldLogConfig(directory, round(max_mb * 1_000_000), vehicle)


def _trust(content: Json, base: Path, fail: Fail) -> Trust | None:
    """``trust``: the public key files sets must be signed by, each read now (absent: none)."""
    section = _optional_section(content, "trust", {"keys", "require"},
                                "{keys: [public key files], require: true}", fail)
    if section is None:
        return None
    paths = section.get("keys")
    if not isinstance(paths, list) or not paths:
        raise fail("trust.keys", "must be a list of public key files (canical keygen's NAME.pub)")
    keys = []
    for i, value in enumerate(paths):
        path = _path(value, base, f"trust.keys[{i}]", fail)
        try:
            keys.append(TrustedKey(read_public(path), str(path)))
        except CanicalError as exc:
            raise fail(f"trust.keys[{i}]", str(exc)) from None
    require = section.get("require", True)
    if not isinstance(require, bool):
        raise fail("trust.require", f"must be true or false, got {require!r}")
    return Trust(tuple(keys), require)


def _imu_set(content: Json, base: Path, fail: Fail) -> Path | None:
    """``imu_set``: one IMU set file (three axes and their coupling) instead of a file per axis."""
    value = content.get("imu_set")
    return None if value is None else _path(value, base, "imu_set", fail)


def _dbc_files(value: Any, base: Path, fail: Fail) -> DbcSet:
    """``dbc``: one DBC file or a list of them, each existing (canical's own frames come beside them)."""
    if isinstance(value, list):
        if not value:
            raise fail("dbc", "an empty list (name one DBC file or several)")
        return DbcSet(_path(v, base, f"dbc[{i}]", fail, must_exist=True) for i, v in enumerate(value))
    return DbcSet((_path(value, base, "dbc", fail, must_exist=True),))


def _bias_tracking(content: Json, inputs: dict[str, InputSource], base: Path,
                   fail: Fail) -> BiasTracking | None:
    """``bias_tracking``: the tracker's settings, its cue and temperature among the inputs."""
    section = content.get("bias_tracking")
    settings = parse_bias_tracking(section, fail)
    if not settings.enabled:
        return None
    if settings.cue_input is not None and settings.cue_input not in inputs:
        raise fail("bias_tracking.cue.input", f"no input {settings.cue_input!r} in inputs "
                   f"(map it there to a DBC signal: {settings.cue_input}: {{signal: MESSAGE.Signal}})")
    temperature: str | None = settings.temperature_input
    if temperature not in inputs:
        if isinstance(section, dict) and "temperature" in section:
            raise fail("bias_tracking.temperature", f"no input {temperature!r} in inputs")
        temperature = None  # the default temp_c, not mapped: learned without temperature
    state = None if settings.state_file is None else _path(settings.state_file, base,
                                                           "bias_tracking.state_file", fail)
    return BiasTracking(settings, temperature, "time_s" if "time_s" in inputs else None, state)


def _bus_options(bus: Json, fail: Fail) -> dict[str, Any]:
    """``bus.options``: python-can's keyword arguments, but none that canical sets itself."""
    options = bus.get("options", {}) or {}
    if not isinstance(options, dict):
        raise fail("bus.options", "must be a mapping of python-can keyword arguments")
    for reserved in ("interface", "channel", "can_filters", "bustype"):
        if reserved in options:
            raise fail(f"bus.options.{reserved}", "is set by canical itself")
    return dict(options)


def _frames(content: Json, dbc: _Dbc) -> _Frames:
    """``frames``: classic, unmultiplexed raw and rate frames with the signals the daemon fills,
    a status frame multiplexed by page."""
    frames = content.get("frames", {}) or {}
    if not isinstance(frames, dict):
        raise dbc.fail("frames", "must be a mapping")
    _no_unknown(frames, {"raw", "rate", "status"}, "frames.", dbc.fail)
    raw_default = _raw_message_of_axes(content, dbc.fail) or "IMU_RAW"
    raw_msg = dbc.message("frames.raw", frames.get("raw", raw_default))
    rate_msg = _rate_frame(content, frames, dbc)
    status_msg = _status_frame(frames, dbc)
    if raw_msg.is_multiplexed() or (rate_msg is not None and rate_msg.is_multiplexed()):
        raise dbc.fail("frames", "the raw and rate frames must not be multiplexed")
    if raw_msg.is_fd or (rate_msg is not None and rate_msg.is_fd):
        raise dbc.fail("frames", "the raw and rate frames must be classic CAN frames")
    if raw_msg.frame_id in {m.frame_id for m in (rate_msg, status_msg) if m is not None}:
        raise dbc.fail("frames.raw", "must differ from the rate and status frames")
    return _Frames(raw_msg, rate_msg, status_msg)


def _status_frame(frames: Json, dbc: _Dbc) -> Message | None:
    """``frames.status``: canical's heartbeat, multiplexed by page, or null (not sent)."""
    if "status" in frames and frames["status"] is None:
        return None
    status_msg = dbc.message("frames.status", frames.get("status", "CANICAL_STATUS"))
    if not status_msg.is_multiplexed():
        raise dbc.fail("frames.status", f"message {status_msg.name} must be multiplexed by Page")
    for sig in STATUS_SIGNALS:
        dbc.need_signal("frames.status", status_msg, sig)
    return status_msg


def _rate_frame(content: Json, frames: Json, dbc: _Dbc) -> Message | None:
    """``frames.rate``: canical's corrected frame, or null (not sent: the own layout is)."""
    if "rate" in frames and frames["rate"] is None:
        if content.get("own_layout") is None:
            raise dbc.fail("frames.rate", "null (not sent) needs own_layout: corrected frames must go out")
        return None
    rate_msg = dbc.message("frames.rate", frames.get("rate", "CANICAL_RATE"))
    for sig in FRAME_SIGNALS:
        dbc.need_signal("frames.rate", rate_msg, sig)
    return rate_msg


def _axes(content: Json, frames: _Frames, dbc: _Dbc, base: Path, *, imu_set: bool) -> tuple[AxisConfig, ...]:
    """``axes``: per axis its raw signal and coefficients file; at least one axis has a file, or
    ``imu_set`` names one file for all three (then no axis names its own). An axis left out is
    absent: a single-axis sensor has no other axes' signals to name."""
    axes_in = _section(content, "axes", dbc.fail)
    _no_unknown(axes_in, set(AXES), "axes.", dbc.fail)
    axes = tuple(_axis(axis, axes_in.get(axis), frames, dbc, base, imu_set=imu_set)
                 if axes_in.get(axis) is not None else AxisConfig(axis, None, None) for axis in AXES)
    if imu_set and not all(a.present for a in axes):
        absent = next(a.axis for a in axes if not a.present)
        raise dbc.fail(f"axes.{absent}", "left out, but imu_set corrects x, y and z: name each axis's raw "
                                         "signal, or configure per-axis coefficients instead of imu_set")
    if not imu_set and not any(a.coefficients for a in axes):
        raise dbc.fail("axes", "no axis has a coefficients file (nor is an imu_set configured)")
    return axes


def _axis(axis: str, entry: Any, frames: _Frames, dbc: _Dbc, base: Path, *, imu_set: bool) -> AxisConfig:
    """``axes.AXIS``: one named axis (its raw signal defaults to canical's ``GyroRawX/Y/Z``)."""
    key = f"axes.{axis}"
    if not isinstance(entry, dict):
        raise dbc.fail(key, "must be a mapping (raw, coefficients)")
    _no_unknown(entry, {"raw", "coefficients", "max_age_s"}, f"{key}.", dbc.fail)
    message, raw_sig = _axis_raw_signal(entry.get("raw", f"GyroRaw{axis.upper()}"), f"{key}.raw",
                                        frames, dbc)
    if "max_age_s" in entry and message is None:
        raise dbc.fail(f"{key}.max_age_s", f"only for an axis in another message than {frames.raw.name}")
    max_age = _positive(entry.get("max_age_s", HELD_AXIS_MAX_AGE_S), f"{key}.max_age_s", dbc.fail)
    if frames.rate is not None:
        for prefix in RATE_SIGNALS.values():
            dbc.need_signal("frames.rate", frames.rate, f"{prefix}{axis.upper()}")
    coeff = entry.get("coefficients")
    if coeff is not None and imu_set:
        raise dbc.fail(f"{key}.coefficients", "not with imu_set: the IMU set holds every axis's model")
    coeff_path = None if coeff is None else _path(coeff, base, f"{key}.coefficients", dbc.fail)
    msg = frames.raw if message is None else dbc.db.get_message_by_name(message)
    units = msg.get_signal_by_name(raw_sig).unit or ""
    return AxisConfig(axis, raw_sig, coeff_path, units, message, max_age)


def _one_axis_per_signal(axes: tuple[AxisConfig, ...], fail: Fail) -> None:
    """Two axes on one raw signal would correct one sensor output with two axes' sets."""
    seen: dict[tuple[str | None, str], str] = {}
    for a in axes:
        if a.raw_signal is None:
            continue
        key = (a.message, a.raw_signal)
        if key in seen:
            raise fail(f"axes.{a.axis}.raw", f"signal {a.raw_signal} is axis {seen[key]}'s already: "
                                             "each axis has a signal of its own")
        seen[key] = a.axis


def _raw_message_of_axes(content: Json, fail: Fail) -> str | None:
    """The raw frame the axes imply when they name ``MESSAGE.Signal`` (None: they name signals of
    ``frames.raw``): their message, or with several, the last axis's (x, y, z order; an IMU
    sends its gyro messages in a burst, the last completes a sample)."""
    axes_in = content.get("axes")
    if not isinstance(axes_in, dict):
        return None
    named = [str(axes_in[a]["raw"]).split(".")[0] for a in AXES
             if isinstance(axes_in.get(a), dict) and isinstance(axes_in[a].get("raw"), str)
             and "." in axes_in[a]["raw"]]
    return named[-1] if named else None


def _axis_raw_signal(value: Any, key: str, frames: _Frames, dbc: _Dbc) -> tuple[str | None, str]:
    """``axes.AXIS.raw``: ``Signal`` of the raw frame, or ``MESSAGE.Signal`` of the raw frame or of
    another message (then held: the message's name is returned beside the signal's)."""
    if not isinstance(value, str) or not value or value.count(".") > 1:
        raise dbc.fail(key, "must name a signal of the raw frame, or be MESSAGE.Signal")
    message, _, signal = value.rpartition(".")
    if not message or message == frames.raw.name:
        dbc.need_signal(key, frames.raw, signal)
        return None, signal
    msg = dbc.message(key, message)
    dbc.need_signal(key, msg, signal)
    if msg.is_multiplexed() or msg.is_fd:
        raise dbc.fail(key, f"message {message} must be a classic, unmultiplexed frame")
    if msg.frame_id in {m.frame_id for m in (frames.rate, frames.status) if m is not None}:
        raise dbc.fail(key, "cannot come from a frame the daemon sends")
    return message, signal


def _counter(content: Json, frames: _Frames, dbc: _Dbc) -> str | None:
    """``counter``: the raw frame's rolling counter signal (absent or null: none, not checked)."""
    counter = content.get("counter")
    if counter is not None:
        if not isinstance(counter, str):
            raise dbc.fail("counter", "must name a signal of the raw frame, or be null")
        dbc.need_signal("counter", frames.raw, counter)
    return counter


#: An input's name: it is a CSV column, a set term's input and a name in generated code.
_INPUT_NAME = re.compile(r"[A-Za-z_][A-Za-z0-9_]{0,63}")


def _inputs(content: Json, frames: _Frames, dbc: _Dbc) -> dict[str, InputSource]:
    """``inputs``: each run-time input's signal (``MESSAGE.Signal``, in a frame the daemon does
    not send) and how old it may get."""
    inputs_in = content.get("inputs", {}) or {}
    if not isinstance(inputs_in, dict):
        raise dbc.fail("inputs", "must be a mapping of input name to {signal, max_age_s}")
    inputs: dict[str, InputSource] = {}
    for name, spec in inputs_in.items():
        key = f"inputs.{name}"
        if str(name).startswith(HELD_AXIS_PREFIX):
            raise dbc.fail(key, f"an input name cannot start with {HELD_AXIS_PREFIX!r}")
        if not isinstance(name, str) or not _INPUT_NAME.fullmatch(name):
            raise dbc.fail(key, "an input name is a letter or _, then letters, digits or _ (at most 64): "
                                "it names a column and a set's input")
        if isinstance(spec, str):
            spec = {"signal": spec}
        if not isinstance(spec, dict):
            raise dbc.fail(key, "must be a mapping {signal: MESSAGE.Signal, max_age_s: seconds}")
        _no_unknown(spec, {"signal", "max_age_s"}, f"{key}.", dbc.fail)
        ref = spec.get("signal")
        if not isinstance(ref, str) or ref.count(".") != 1:
            raise dbc.fail(f"{key}.signal", "must be MESSAGE.Signal")
        msg_name, sig_name = ref.split(".")
        msg = dbc.message(f"{key}.signal", msg_name)
        dbc.need_signal(f"{key}.signal", msg, sig_name)
        if msg.is_multiplexed():
            raise dbc.fail(f"{key}.signal", f"message {msg_name} is multiplexed (not supported for inputs)")
        if msg.frame_id in {m.frame_id for m in (frames.rate, frames.status) if m is not None}:
            raise dbc.fail(f"{key}.signal", "cannot come from a frame the daemon sends")
        max_age = _positive(spec.get("max_age_s", 1.0), f"{key}.max_age_s", dbc.fail)
        inputs[str(name)] = InputSource(str(name), msg_name, sig_name, max_age)
    return inputs


def _own_layout_output(content: Json, frames: _Frames, inputs: dict[str, InputSource], dbc: _Dbc,
                       channel: str, j1939: J1939Source) -> OwnLayoutOutput | None:
    """``own_layout``: send each corrected frame in the raw frame's own layout too, at ``id``,
    on the sensor's bus or, with ``channel``, on another one (absent: not sent)."""
    spec = content.get("own_layout")
    if spec is None:
        return None
    held = list(dict.fromkeys(s.message for n, s in inputs.items() if n.startswith(HELD_AXIS_PREFIX)))
    if not isinstance(spec, dict):
        raise dbc.fail("own_layout", "must be a mapping {id: CAN id, extended: bool, channel: name}")
    _no_unknown(spec, {"id", "extended", "channel", "ids"}, "own_layout.", dbc.fail)
    extended = spec.get("extended", frames.raw.is_extended_frame)
    if not isinstance(extended, bool):
        raise dbc.fail("own_layout.extended", f"must be true or false, got {extended!r}")
    frame_id = _can_id(spec.get("id"), extended, "own_layout.id", dbc.fail)
    held_ids = _held_ids(spec.get("ids"), held, dbc)
    out_channel = spec.get("channel")
    if out_channel is not None and (not isinstance(out_channel, str) or not out_channel):
        raise dbc.fail("own_layout.channel", "must be a non-empty interface name")
    if out_channel == channel:
        out_channel = None
    out_ids = [("own_layout.id", frame_id, extended),
               *((f"own_layout.ids.{n}", i, e) for n, i, e in held_ids)]
    if out_channel is None:  # on the sensor's bus: not an id the daemon reads or sends already
        read = [frames.raw, *(dbc.db.get_message_by_name(s.message) for s in inputs.values())]
        sent = [m for m in (frames.rate, frames.status) if m is not None]
        for key, out_id, out_ext in out_ids:
            for msg, match in [*((m, frame_match(m, j1939)) for m in read),
                               *((m, frame_match(m)) for m in sent)]:
                if match.matches(out_id, out_ext):
                    what = "id" if match.exact else f"group ({match.describe()})"
                    raise dbc.fail(key, f"{out_id:#x} is {msg.name}'s {what} on the same bus "
                                        "(give another id, or another channel)")
    if len({(i, e) for _, i, e in out_ids}) < len(out_ids):
        raise dbc.fail("own_layout.ids", "two messages sent at the same id")
    return OwnLayoutOutput(frame_id, extended, out_channel, held_ids)


def _can_id(value: Any, extended: bool, key: str, fail: Fail) -> int:
    top = 0x1FFFFFFF if extended else 0x7FF
    if not isinstance(value, int) or isinstance(value, bool) or not 0 <= value <= top:
        raise fail(key, f"must be a CAN id 0..{top:#x}, got {value!r}")
    return value


def _held_ids(spec: Any, held: list[str], dbc: _Dbc) -> tuple[tuple[str, int, bool], ...]:
    """``own_layout.ids``: the id of each other message an axis comes in (each of them, no other)."""
    if spec is None and not held:
        return ()
    if not isinstance(spec, dict):
        raise dbc.fail("own_layout.ids", f"the axes come from several messages: give each other one's "
                                         f"id ({', '.join(f'{m}: ID' for m in held)})")
    unknown = sorted(set(spec) - set(held), key=str)
    if unknown:
        others = ", ".join(held) or "none"
        raise dbc.fail(f"own_layout.ids.{unknown[0]}", f"no axis comes in {unknown[0]} (ids are for the "
                                                       f"axes' other messages: {others})")
    out = []
    for name in held:
        if name not in spec:
            raise dbc.fail("own_layout.ids", f"no id for {name}, which an axis comes in")
        extended = dbc.db.get_message_by_name(name).is_extended_frame
        out.append((name, _can_id(spec[name], extended, f"own_layout.ids.{name}", dbc.fail), extended))
    return tuple(out)


def _j1939_source(content: Json, fail: Fail) -> J1939Source:
    """``j1939``: which source address J1939 messages are matched with (absent: the DBC's)."""
    section = _optional_section(content, "j1939", {"source_address", "messages"},
                                "{source_address: any or 0..253, messages: [...] or all}", fail)
    if section is None:
        return None
    try:
        return parse_j1939_source(section.get("source_address"), "source_address")
    except ValueError as exc:
        raise fail("j1939.source_address", str(exc).split(": ", 1)[1]) from None


def _j1939_messages(content: Json, fail: Fail) -> tuple[str, ...]:
    """``j1939.messages``: the messages that are J1939 parameter groups though the DBC does not say
    so (no ``VFrameFormat``/``ProtocolType``): a list of names, or ``all`` (every extended-id one)."""
    section = content.get("j1939")
    if not isinstance(section, dict) or section.get("messages") is None:
        return ()
    value = section["messages"]
    if value == ALL_EXTENDED:
        return (ALL_EXTENDED,)
    if not isinstance(value, list) or not value or not all(isinstance(v, str) and v for v in value):
        raise fail("j1939.messages", f"must be a list of message names or '{ALL_EXTENDED}'")
    return tuple(value)


def _raw_frames_can_match(frames: _Frames, axes: tuple[AxisConfig, ...], dbc: _Dbc,
                          j1939: J1939Source) -> None:
    """Refuse a configuration under which a raw frame can never be matched: a source address is
    configured for J1939, but the raw message is matched by its exact id, whose source differs
    (a vendor's DBC without the J1939 attributes: "configuration OK", then no frame ever)."""
    if not isinstance(j1939, int):
        return
    messages = {frames.raw.name: "frames.raw"} | {a.message: f"axes.{a.axis}.raw" for a in axes if a.message}
    for name, key in messages.items():
        message = dbc.db.get_message_by_name(name)
        match = frame_match(message, j1939)
        if message.is_extended_frame and match.exact and message.frame_id & 0xFF != j1939:
            raise dbc.fail(key, f"message {name} is matched by its exact id 0x{message.frame_id:08x}, "
                                f"whose source address 0x{message.frame_id & 0xFF:02x} is not "
                                f"j1939.source_address 0x{j1939:02x}: if it is a J1939 parameter group, "
                                f"list it under j1939.messages (or messages: {ALL_EXTENDED})")


def _device(content: Json, fail: Fail) -> DeviceSource | None:
    """``device``: the IMU as a CANopen node whose own sets are used (absent: files only)."""
    device_in = _optional_section(content, "device", {"node", "timeout_s"},
                                  "{node: CANopen node id, timeout_s: seconds}", fail)
    if device_in is None:
        return None
    node = device_in.get("node")
    if not isinstance(node, int) or isinstance(node, bool) or not 1 <= node <= 127:
        raise fail("device.node", f"must be a CANopen node id 1..127, got {node!r}")
    return DeviceSource(node, _positive(device_in.get("timeout_s", 1.0), "device.timeout_s", fail))


def _optional_section(content: Json, name: str, allowed: set[str], shape: str, fail: Fail) -> Json | None:
    """An optional mapping section of the configuration, its keys checked (absent: None)."""
    section = content.get(name)
    if section is None:
        return None
    if not isinstance(section, dict):
        raise fail(name, f"must be a mapping {shape}")
    _no_unknown(section, allowed, f"{name}.", fail)
    return section


def _no_unknown(section: Mapping[str, Any], allowed: set[str], prefix: str, fail: Fail) -> None:
    for key in section:
        if key not in allowed:
            expected = ", ".join(sorted(allowed, key=str))
            raise fail(f"{prefix}{key}", f"unknown key (expected one of {expected})")


def _section(content: Json, key: str, fail: Fail) -> Json:
    value = content.get(key)
    if not isinstance(value, dict):
        raise fail(key, "missing or not a mapping")
    return value


def _text(section: Json, key: str, name: str, fail: Fail) -> str:
    value = section.get(key)
    if not isinstance(value, str) or not value:
        raise fail(name, "missing or not a non-empty string")
    return value


def _optional_text(content: Json, key: str, fail: Fail) -> str | None:
    value = content.get(key)
    if value is None:
        return None
    if not isinstance(value, str | int) or isinstance(value, bool) or value == "":
        raise fail(key, "must be a non-empty string")
    return str(value)


def _positive(value: Any, key: str, fail: Fail) -> float:
    number = isinstance(value, int | float) and not isinstance(value, bool)
    try:
        seconds = float(value) if number else math.nan  # an int beyond a float: OverflowError
    except OverflowError:
        seconds = math.inf
    if not math.isfinite(seconds) or seconds <= 0:
        raise fail(key, f"must be a positive number of seconds, got {value!r}")
    return seconds


def _path(value: Any, base: Path, key: str, fail: Fail, *, must_exist: bool = False) -> Path:
    if not isinstance(value, str) or not value:
        raise fail(key, "missing or not a file path")
    path = Path(value)
    if not path.is_absolute():
        path = base / path
    if must_exist and not _is_file(path):
        raise fail(key, f"file {one_line(str(path), 120)} not found")
    return path


def _is_file(path: Path) -> bool:
    """Whether ``path`` is a file; a name the system cannot look up (too long, a NUL byte) is not
    one. Why: ``Path.is_file`` raises on those (the fuzzer's 5,000-character ``dbc:``), a traceback."""
    try:
        return path.is_file()
    except (OSError, ValueError):
        return False
