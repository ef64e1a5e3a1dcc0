"""The daemon's configuration keys, documented, and a probe of which keys the parser accepts.

The parser (``canical/bus/daemon_config.py``) has no table of its keys, so the documentation
keeps one here and :func:`undocumented_keys` holds the two together: it asks the parser itself,
by adding an unknown key to each section of a valid configuration and reading the keys its
one-line error lists (``unknown key (expected one of ...)``). The reference page refuses to build,
and ``tests/docs/test_config_keys.py`` fails, when the parser accepts a key this table lacks or
the table lists one it refuses. :func:`default_checks` does the same for the defaults.
"""

from __future__ import annotations

import re
import tempfile
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path
from typing import Any

ROOT = Path(__file__).resolve().parents[2]
EXAMPLE = ROOT / "services" / "canical-can0.yaml"
DBC = ROOT / "dbc" / "canical.dbc"
PROBE = "zz_docs_probe"
#: In the table, AXIS stands for each of x, y, z and NAME for any input name.
AXES = ("x", "y", "z")


@dataclass(frozen=True)
class Key:
    key: str
    default: str
    check: str
    meaning: str


def _tracking_keys() -> tuple[Any, ...]:
    """The ``bias_tracking`` keys, from the table beside their parser."""
    from canical.tracking.settings import KEYS as TRACKING_KEYS

    return TRACKING_KEYS


INTRODUCTION = """\
`canical serve --config FILE` (and `record`, `apply --config`) read one YAML file. Relative paths
are taken from the file's folder. The whole file is checked before the daemon starts: a defect
is refused with one line naming the key and exit status 2, e.g.
`can0.yaml: inputs.temp_c.signal: message IMU_RAWW not in canical.dbc`; an unknown key is refused
the same way. `canical serve --config FILE --check` also loads every set and stops.
*AXIS* is `x`, `y` or `z`; *NAME* is an input's name as the sets' effect terms use it.
"required" means the key has no default."""

KEYS: tuple[Key, ...] = (
    Key("bus", "required", "a mapping", "the CAN interface, as python-can opens it"),
    Key(
        "bus.interface",
        "required",
        "non-empty string",
        "python-can interface: `socketcan` on the vehicle, `virtual` for tests, `pcan`, `kvaser`…",
    ),
    Key(
        "bus.channel",
        "required",
        "non-empty string",
        "interface channel, e.g. `can0`; `--channel` (the systemd unit's `%i`) overrides it",
    ),
    Key(
        "bus.options",
        "`{}`",
        "a mapping; not `interface`, `channel`, `can_filters`, `bustype`",
        "extra python-can keyword arguments (e.g. `bitrate` for pcan)",
    ),
    Key(
        "dbc",
        "required",
        "an existing file, or a list of them, that cantools loads (non-strictly: a message with overlapping "
        "signals is refused only if canical uses it); a name or id two files define differently is refused",
        "the frame layouts: the one source of truth; canical's own frames (`CANICAL_RATE`, "
        "`CANICAL_STATUS`…) are loaded beside them from the shipped `canical.dbc` where the files "
        "do not define them",
    ),
    Key(
        "sensor",
        "`null` (any)",
        "non-empty string or number",
        "sets calibrated for another sensor id are refused",
    ),
    Key("frames", "`{}`", "a mapping", "which DBC messages the daemon reads and sends"),
    Key(
        "frames.raw",
        "the message the axes name as `MESSAGE.Signal`, else `IMU_RAW`",
        "a DBC message, not multiplexed, classic CAN (standard or extended id), not the rate or status frame",
        "the IMU's raw frame, one correction per frame",
    ),
    Key(
        "frames.rate",
        "`CANICAL_RATE`",
        "a DBC message, not multiplexed, classic CAN, with `RateAXIS`, "
        "`OutOfSpanAXIS`, `UncalibratedAXIS` per axis and `Stale`, `CounterGap`, `SetTag`, `Counter`; "
        "or `null`: not sent (needs `own_layout`, whose frame is then the corrected frame)",
        "the corrected frame, sent once per raw frame",
    ),
    Key(
        "frames.status",
        "`CANICAL_STATUS`",
        "a DBC message multiplexed by `Page`, with `State`, `FramesIn`, `SetId`, `Reloads`; or `null` "
        "(not sent: a vehicle bus that takes no frame of canical's own)",
        "the heartbeat, every `status_period_s`",
    ),
    Key(
        "axes",
        "required",
        "a mapping with at least one axis that has `coefficients`, or every axis without them and `imu_set`",
        "the raw signal and coefficient set of each axis",
    ),
    Key("axes.AXIS", "absent (not read, not corrected: a single-axis sensor names one axis)", "a mapping",
        "one axis; an axis left out is never read, and in `CANICAL_RATE` goes out uncalibrated"),
    Key(
        "axes.AXIS.raw",
        "`GyroRawX`, `GyroRawY`, `GyroRawZ`",
        "a signal of the raw frame, or `MESSAGE.Signal` of any classic, unmultiplexed message; "
        "with several messages the last axis's is the raw frame (unless `frames.raw` says) and the "
        "others are held at their latest value",
        "the axis's raw signal: the physical value the DBC gives (its scale and offset applied), "
        "the same value a session's `raw` column holds",
    ),
    Key(
        "axes.AXIS.max_age_s",
        "`0.1`",
        "positive number of seconds; only for an axis in another message than the raw frame",
        "older than this when the raw frame comes sets the corrected frame's Stale flag; never "
        "received: the axis is Uncalibrated",
    ),
    Key(
        "axes.AXIS.coefficients",
        "`null` (axis uncalibrated: rate 0, flag Uncalibrated)",
        "a file path; the set is loaded and checked at start and on every reload",
        "the axis's coefficient set (YAML)",
    ),
    Key(
        "imu_set",
        "`null` (a set file per axis)",
        "a file path to an IMU set (`canical calibrate x.csv y.csv z.csv`); no axis names its own "
        "`coefficients`",
        "the three axes' models and the coupling between them, loaded, checked and reloaded as one: "
        "the corrected frame carries the coupled rates",
    ),
    Key(
        "counter",
        "`null` (no counter check)",
        "a signal of the raw frame, or `null` (no counter check)",
        "the raw frame's rolling counter: a jump sets CounterGap",
    ),
    Key("inputs", "`{}`", "a mapping of NAME to a signal", "run-time inputs of the sets' effect terms"),
    Key(
        "inputs.NAME",
        "",
        "`MESSAGE.Signal` text, or a mapping with the keys below",
        "where input NAME comes from; its latest value is held",
    ),
    Key(
        "inputs.NAME.signal",
        "required",
        "`MESSAGE.Signal` of the DBC; not multiplexed; not a frame the daemon sends",
        "the signal carrying the input (e.g. `IMU_RAW.Temperature`, `IMU_AUX.Uptime` for `time_s`)",
    ),
    Key(
        "inputs.NAME.max_age_s",
        "`1.0`",
        "positive number of seconds",
        "older than this sets the corrected frame's Stale flag; never received: the axis is Uncalibrated",
    ),
    Key(
        "device",
        "`null` (sets from files only)",
        "a mapping",
        "take the sets from the IMU over CANopen SDO at start and on SIGHUP (its IMU set whole, "
        "coupling included, when it runs one); files are the fallback",
    ),
    Key("device.node", "required", "integer 1..127", "the IMU's CANopen node id (e.g. `0x10`)"),
    Key("device.timeout_s", "`1.0`", "positive number of seconds", "SDO timeout"),
    Key(
        "own_layout",
        "`null` (not sent)",
        "a mapping",
        "the corrected frame in the IMU's own layout: the raw frame's message re-encoded with each axis's "
        "signal its corrected value (saturated to the signal's range, rounded as cantools does; an "
        "uncalibrated axis as it came), every other signal copied through; `CANICAL_RATE` is still sent",
    ),
    Key(
        "own_layout.id",
        "required",
        "a CAN id (standard up to `0x7FF`, extended up to `0x1FFFFFFF`); on the sensor's bus not an id "
        "the daemon reads or sends",
        "the id the own-layout frame is sent at",
    ),
    Key("own_layout.extended", "the raw frame's", "`true` or `false`", "whether that id is extended"),
    Key(
        "own_layout.ids",
        "required when axes come in several messages, else absent",
        "a mapping of each other message an axis comes in to a CAN id (extended as that message is); "
        "all ids distinct, none the daemon reads or sends on the same bus",
        "where each of those messages goes out, re-encoded from its latest frame with its axes "
        "corrected, whenever the raw frame is",
    ),
    Key(
        "own_layout.channel",
        "`null` (the sensor's bus)",
        "a non-empty interface name",
        "another channel of the same interface: a one-way gateway, sensor bus in, this bus out "
        "(nothing is read from it)",
    ),
    Key("j1939", "`null`", "a mapping",
        "messages the DBC marks as J1939 are matched by parameter group (PGN), priority and a PDU1 "
        "destination ignored, and by source address as below"),
    Key("j1939.source_address", "`null` (the DBC's)", "`any`, or an address 0..253",
        "the source address J1939 messages are matched with (the IMU's claimed address), or any"),
    Key("j1939.messages", "`null` (the DBC's attributes)", "a list of message names, or `all`",
        "messages that are J1939 parameter groups though the DBC does not say so (a vendor's file "
        "without `VFrameFormat`/`ProtocolType`); `all`: every extended-id message of the DBC files"),
    Key("trust", "`null` (sets not authenticated: one warning at start)", "a mapping",
        "only sets the calibration lab signed (`canical sign`): one without a valid signature from a "
        "trusted key, for another sensor, or older than the running set (a rollback) is refused as a "
        "corrupt set is, at start, on SIGHUP and on a file change (see Signed sets)"),
    Key("trust.keys", "required", "a non-empty list of public key files (`canical keygen`'s NAME.pub)",
        "the keys a set's signature must be by; each read when the configuration is"),
    Key("trust.require", "`true`", "`true` or `false`",
        "`false`: a set's signature is checked and a problem is a warning, the set used all the same "
        "(while a fleet's sets are being signed)"),
    Key("status_period_s", "`1.0`", "positive number of seconds", "status frames and systemd STATUS"),
    Key(
        "watch_period_s",
        "`1.0`",
        "positive number of seconds",
        "how often the coefficient files are checked for changes",
    ),
    *(
        Key("bias_tracking", "`null` (off)", "a mapping",
            "learn each axis's bias at standstills and subtract it (see On the vehicle)"),
        *(Key(f"bias_tracking.{k.key}", k.default if k.default in ("required", "none") else f"`{k.default}`",
              k.check, k.meaning) for k in _tracking_keys()),
    ),
    Key("field_log", "`null` (none)", "a mapping, with `bias_tracking` enabled",
        "keep each standstill decision and power-on as a record for the fleet (see Fleet)"),
    Key("field_log.dir", "required", "folder path", "where the segments are written (created if missing)"),
    Key("field_log.max_mb", "`64`", "number of megabytes, 0.1 to 1000000",
        "the segments' size bound: the oldest are removed beyond it"),
    Key("field_log.vehicle_id", "required", "1-64 letters, digits, `.`, `_` or `-`",
        "the vehicle's id, in every record"),
)


def expand(key: str) -> Iterator[str]:
    """A table key as the concrete keys it stands for (AXIS: each axis)."""
    if "AXIS" in key:
        for axis in AXES:
            yield key.replace("AXIS", axis)
    else:
        yield key


def documented_keys() -> set[str]:
    return {k for key in KEYS for k in expand(key.key)}


# --- asking the parser ----------------------------------------------------------------------------


def base_content() -> dict[str, Any]:
    """The deployable example, with the repository's DBC and the device source switched on."""
    import yaml

    content = yaml.safe_load(EXAMPLE.read_text(encoding="utf-8"))
    content["dbc"] = str(DBC)
    content["device"] = {"node": 0x10, "timeout_s": 1.0}
    content["own_layout"] = {"id": 0x298}
    content["j1939"] = {"source_address": "any"}
    # on, with the example's supply_v input standing in for a cue, so field_log (which needs it) is probed too
    content["bias_tracking"] = {"enabled": True, "cue": {"input": "supply_v", "below": 0.1}}
    content["field_log"] = {"dir": tempfile.gettempdir(), "max_mb": 1, "vehicle_id": "probe"}
    content["trust"] = {"keys": [str(_probe_public_key())], "require": True}
    return content


def _probe_public_key() -> Path:
    """A public key file for the probe's ``trust`` section (the parser reads each key it names)."""
    from canical.files.key_file import write_key_pair
    from canical.sets.signing import new_seed, public_of

    seed = new_seed()
    return write_key_pair(Path(tempfile.mkdtemp(prefix="canical-docs-")) / "probe", seed, public_of(seed))[1]


def parse_error(content: dict[str, Any]) -> str | None:
    """The parser's one-line error for this content, or None when it is accepted."""
    import yaml

    from canical.bus.daemon_config import load_config
    from canical.errors import CanicalError

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "probe.yaml"
        path.write_text(yaml.safe_dump(content), encoding="utf-8")
        try:
            load_config(path)
        except CanicalError as exc:
            return str(exc)
    return None


def _at(content: dict[str, Any], path: tuple[str, ...]) -> Any:
    for part in path:
        content = content[part]
    return content


def accepted_keys() -> set[str]:
    """Every key the parser accepts, found by probing each section of a valid configuration.

    A section answers an unknown key with the keys it expects; one that takes any name (inputs)
    answers otherwise and stands as NAME, probed through one of its entries; one that takes
    any keyword argument (bus.options) accepts the probe and has no sub-keys of its own.
    """
    import copy

    base = base_content()
    if parse_error(base) is not None:
        raise RuntimeError(f"the example configuration does not parse: {parse_error(base)}")
    found: set[str] = set()

    def visit(path: tuple[str, ...], shown: tuple[str, ...]) -> None:
        probe = copy.deepcopy(base)
        _at(probe, path)[PROBE] = 1
        error = parse_error(probe) or ""
        wanted = ".".join((*path, PROBE)) + ": unknown key (expected one of "
        match = re.search(re.escape(wanted) + r"([^)]*)\)", error)
        if match:
            names = [n.strip() for n in match.group(1).split(",")]
            for name in names:
                found.add(".".join((*shown, name)))
                if isinstance(_at(base, path).get(name), dict):
                    visit((*path, name), (*shown, name))
        elif error and _at(base, path):
            # any name: probe one entry as NAME
            first = next(iter(_at(base, path)))
            found.add(".".join((*shown, "NAME")))
            if isinstance(_at(base, path)[first], dict):
                visit((*path, first), (*shown, "NAME"))

    visit((), ())
    return found


def undocumented_keys() -> tuple[set[str], set[str]]:
    """(accepted but not documented, documented but not accepted)."""
    accepted, documented = accepted_keys(), documented_keys()
    return accepted - documented, documented - accepted


def default_checks() -> list[tuple[str, str, object]]:
    """(key, documented default, what the parser gives when the key is left out), for each
    key whose default is a single value."""
    from canical.bus.daemon_config import DaemonConfig

    minimal = {
        "bus": {"interface": "virtual", "channel": "docs"},
        "dbc": str(DBC),
        "axes": {"x": {}, "z": {"coefficients": "imu-z.yaml"}},
        "inputs": {"temp_c": {"signal": "IMU_RAW.Temperature"}},
        "device": {"node": 16},
    }
    import yaml

    from canical.bus.daemon_config import load_config

    with tempfile.TemporaryDirectory() as folder:
        path = Path(folder) / "minimal.yaml"
        path.write_text(yaml.safe_dump(minimal), encoding="utf-8")
        cfg: DaemonConfig = load_config(path)
    documented = {k.key: k.default for k in KEYS}
    by_axis = {a.axis: a for a in cfg.axes}
    assert cfg.device is not None
    return [
        ("frames.raw", documented["frames.raw"].split(", else ")[-1], cfg.raw_message),
        ("frames.rate", documented["frames.rate"], cfg.rate_message),
        ("frames.status", documented["frames.status"], cfg.status_message),
        ("counter", documented["counter"].split(" ")[0], cfg.counter_signal),
        ("axes.AXIS.raw", documented["axes.AXIS.raw"].split(", ")[0], by_axis["x"].raw_signal),
        (
            "axes.AXIS.coefficients",
            documented["axes.AXIS.coefficients"].split(" ")[0],
            by_axis["x"].coefficients,
        ),
        ("inputs.NAME.max_age_s", documented["inputs.NAME.max_age_s"], cfg.inputs["temp_c"].max_age_s),
        ("device.timeout_s", documented["device.timeout_s"], cfg.device.timeout_s),
        ("status_period_s", documented["status_period_s"], cfg.status_period_s),
        ("watch_period_s", documented["watch_period_s"], cfg.watch_period_s),
        ("sensor", documented["sensor"].split(" ")[0], cfg.sensor),
        ("bus.options", documented["bus.options"], cfg.bus_options),
        ("trust", documented["trust"].split(" ")[0], cfg.trust),
    ]


def as_yaml_value(value: object) -> str:
    """A parsed default as the docs write it: `null`, `1.0`, `IMU_RAW`, `{}`."""
    if value is None:
        return "`null`"
    if value == {}:
        return "`{}`"
    return f"`{value}`"
