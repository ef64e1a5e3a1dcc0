"""The coefficient sets a daemon corrects with, as one immutable value that is replaced whole.

Why a single value: the processing loop reads ``daemon.sets`` once per frame and uses only
what it read, so a reload (build and validate everything, then one assignment) can never make
a frame use half of an old set and half of a new one. An axis whose file did not change keeps
its :class:`~canical.sets.corrector.Corrector` object, and with it the state of a direction term.

A candidate set is validated completely before it can replace anything: the file's own checks
(schema, CRC, every field), then that it is for this axis and sensor, that every run-time
input it needs is mapped in the configuration, and that it evaluates to finite rates across
its span. A set that fails is reported and the previous one stays in use. With ``trust:`` in the
configuration the set must also be signed by a trusted key for its sensor, and not be older than
the set it replaces (:mod:`canical.sets.signing`): checked at load, nothing per frame.
"""

from __future__ import annotations

import os
import struct
import zlib
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from canical.bus.daemon_config import DaemonConfig
from canical.errors import CanicalError, one_line
from canical.frames.imu_frames import SET_TAG_MASK
from canical.sets import signed_file
from canical.sets.admission import raw_units_problem
from canical.sets.coefficients import CoefficientSet
from canical.sets.corrector import Corrector
from canical.sets.imu_set import AXES, ImuSet, Matrix, imu_set_crc
from canical.sets.signing import SignedContent

SOURCE_NONE = 0
SOURCE_FILE = 1
SOURCE_DEVICE = 2  # read from the IMU over CANopen SDO (config ``device``)

FileStamp = tuple[int, int, int] | None


@dataclass(frozen=True)
class SetsNote:
    """One thing that happened while building sets, to log: ``refused`` when a set was refused
    and the one in use (or none) kept, which an operator must see (a warning); else news."""

    text: str
    refused: bool = False

    def __str__(self) -> str:
        return self.text


@dataclass(frozen=True)
class AxisSet:
    """What one axis corrects with; ``corrector`` None means the axis goes out uncalibrated."""

    axis: str
    raw_signal: str | None  # None: the axis is absent from the configuration (never corrected)
    corrector: Corrector | None = None
    set_id: int = 0
    source: int = SOURCE_NONE
    reloads: int = 0
    path: Path | None = None
    stamp: FileStamp = None  # the file as last looked at (loaded or refused), to notice changes
    version: int | None = None  # the running set's signed version (None: not verified), against rollback

    @property
    def required_inputs(self) -> tuple[str, ...]:
        return self.corrector.required_inputs if self.corrector is not None else ()


@dataclass(frozen=True)
class ActiveSets:
    """The three axes in x, y, z order, and the identifier of the combination.

    From an IMU set (config ``imu_set``) the axes come with ``coupling``, the matrix their
    corrected rates go through (``None``: per-axis sets, no coupling), and ``combined_id`` is the
    IMU set's own id (its CRC), the one ``calibrate`` and ``apply`` print."""

    axes: tuple[AxisSet, ...]
    combined_id: int
    tag: int  # the low bits of combined_id (SET_TAG_MASK): sent in every corrected frame
    inputs: tuple[str, ...]  # union of the inputs the sets need
    coupling: Matrix | None = None

    @property
    def complete(self) -> bool:
        return all(a.corrector is not None for a in self.axes)

    def describe(self) -> str:
        axes = " ".join(f"{a.axis}={a.set_id:08x}" if a.corrector else f"{a.axis}=none" for a in self.axes)
        return axes if self.coupling is None else f"imu set {self.combined_id:08x} ({axes}, coupled)"


def file_stamp(path: Path | None) -> FileStamp:
    """Identity of a file's current content as far as stat tells (None: absent)."""
    if path is None:
        return None
    try:
        st = os.stat(path)
    except OSError:
        return None
    return (st.st_mtime_ns, st.st_size, st.st_ino)


def files_changed(current: ActiveSets) -> bool:
    """Whether any set file differs from when it was last looked at (a few ``stat`` calls)."""
    return any(ax.path is not None and file_stamp(ax.path) != ax.stamp for ax in current.axes)


def build(axes: tuple[AxisSet, ...], imu: ImuSet | None = None) -> ActiveSets:
    """Combine per-axis sets (or the axes of ``imu``, with its coupling) into the value the loop reads."""
    if imu is not None:
        combined = imu_set_crc(imu)
    else:
        combined = zlib.crc32(struct.pack(">" + "I" * len(axes), *(a.set_id for a in axes))) & 0xFFFFFFFF
    names = tuple(dict.fromkeys(n for a in axes for n in a.required_inputs))
    return ActiveSets(axes=axes, combined_id=combined, tag=combined & SET_TAG_MASK, inputs=names,
                      coupling=None if imu is None else imu.coupling)


@dataclass(frozen=True)
class Origin:
    """What verifying a set's signature against ``trust:`` found."""

    version: int | None = None  # the signed version (None: not verified: no trust, or not required)
    warning: str | None = None  # a signature problem let through because trust.require is false


def verify_origin(config: DaemonConfig, signed: SignedContent, running: int | None, source: str) -> Origin:
    """Check a set's signature as ``trust:`` says: refused (one CanicalError line) when required
    and not signed by a trusted key for its sensor, or older than ``running``; warned otherwise."""
    trust = config.trust
    if trust is None:
        return Origin()
    try:
        record = signed_file.verified(signed, trust.keys, running, source)
    except CanicalError as exc:
        if trust.require:
            raise
        return Origin(warning=f"{exc} (adopted: trust.require is false)")
    return Origin(record.version)


def load_axis(config: DaemonConfig, axis: str, path: Path, running: int | None = None) -> Corrector:
    """Load and fully validate the set for ``axis``; any defect is one CanicalError line (a missing
    file names the configuration key that points at it, where a user fixes it)."""
    return load_axis_origin(config, axis, path, running)[0]


def load_axis_origin(config: DaemonConfig, axis: str, path: Path,
                     running: int | None) -> tuple[Corrector, Origin]:
    """:func:`load_axis`, and the signature verified against ``trust:`` (``running``: the version
    of the set it would replace)."""
    if not _exists(Path(path)):
        raise CanicalError(f"{one_line(str(path), 120)}: coefficient file not found "
                           f"(axes.{axis}.coefficients in {config.path})")
    cset, signed = signed_file.load_set(path)
    origin = verify_origin(config, signed, running, str(path))
    return check_set(config, axis, cset, path), origin


def _exists(path: Path) -> bool:
    """Whether ``path`` exists; a name the system cannot look up (too long, a NUL byte) does not.
    Why: ``Path.exists`` raises on those (the fuzzer's 5,000-character ``coefficients:``)."""
    try:
        return path.exists()
    except (OSError, ValueError):
        return False


def check_set(config: DaemonConfig, axis: str, cset: CoefficientSet, path: Path | str) -> Corrector:
    """Validate a loaded set for ``axis`` (from a file or the device) and build its corrector."""
    if cset.axis != axis:
        raise CanicalError(f"{path}: set is for axis {cset.axis}, configured for axis {axis}")
    if config.sensor is not None and cset.sensor_id != config.sensor:
        raise CanicalError(
            f"{path}: set is for sensor {cset.sensor_id}, configured sensor is {config.sensor}"
        )
    units = next((a.raw_units for a in config.axes if a.axis == axis), "")
    problem = raw_units_problem(cset.raw_units, units)
    if problem:
        raise CanicalError(f"{path}: axis {axis}: {problem}")
    corrector = Corrector(cset)
    missing = [n for n in corrector.required_inputs if n not in config.inputs]
    if missing:
        raise CanicalError(
            f"{path}: set needs input(s) {', '.join(missing)}, not mapped under 'inputs' in {config.path}"
        )
    lo, hi = cset.span_raw
    probe = np.linspace(lo, hi, 33)
    inputs = {n: np.ones_like(probe) for n in corrector.required_inputs}
    try:
        rate, _ = corrector.correct(probe, inputs)
    except Exception as exc:  # a set that cannot be evaluated must not reach the loop
        raise CanicalError(f"{path}: set cannot be evaluated ({exc})") from None
    if not np.all(np.isfinite(rate)):
        raise CanicalError(f"{path}: set gives non-finite rates inside its span")
    corrector.reset()
    return corrector


def initial(config: DaemonConfig) -> tuple[ActiveSets, list[SetsNote]]:
    """The sets at start; problems are returned as messages (the axis starts uncalibrated)."""
    empty = tuple(AxisSet(a.axis, a.raw_signal, path=config.imu_set or a.coefficients) for a in config.axes)
    if config.device is not None:
        return from_device(config, build(empty))
    return reload(config, build(empty), force=True)


def from_device(config: DaemonConfig, current: ActiveSets) -> tuple[ActiveSets, list[SetsNote]]:
    """The IMU's own active sets (config ``device``), each validated like a file; files for the rest.

    The sensor carries its calibration: an axis the device has a valid set for uses it
    (``source`` 2); an axis it has none for, or every axis when the device does not answer,
    falls back to the configured file. The file's stamp is recorded, so only a later change
    of the file (an operator's act) replaces a set read from the device; SIGHUP reads the
    device again. A set whose id is already running keeps its corrector (and its state).
    """
    from canical.device.can_network import open_network, sdo_client_filters
    from canical.device.sdo_download import pull_active

    device = config.device
    assert device is not None
    where = f"device node 0x{device.node:02x}"
    pulled: dict[str, CoefficientSet] = {}
    pulled_imu: ImuSet | None = None
    signatures: dict[str, bytes] = {}
    messages: list[SetsNote] = []
    try:
        network = open_network(config.interface, config.channel, can_filters=sdo_client_filters(device.node),
                               **config.bus_options)
        try:
            # An axis the configuration leaves out is not corrected, whatever the device holds for it.
            present = tuple(a.axis for a in config.axes if a.present)
            got = pull_active(network, device.node, present, device.timeout_s)
            pulled, pulled_imu, signatures = got.sets, got.imu, got.signatures
        finally:
            network.disconnect()
    except CanicalError as exc:
        messages.append(SetsNote(f"{where}: {exc}; using the coefficient files"))
    versions: dict[str, int | None] = {}
    if config.trust is not None and (pulled or pulled_imu is not None):
        try:
            versions = device_versions(config, current, DeviceSets(pulled, pulled_imu, signatures), where)
        except CanicalError as exc:
            if config.trust.require:
                messages.append(SetsNote(f"{exc}; using the coefficient files", refused=True))
                pulled, pulled_imu = {}, None
            else:
                messages.append(SetsNote(f"{exc} (adopted: trust.require is false)"))
    if pulled_imu is not None:
        try:
            return _device_imu(config, current, pulled_imu, where, versions.get("imu"))
        except CanicalError as exc:
            messages.append(SetsNote(f"imu set: {exc}; using the coefficient files"))
    files, file_messages = reload(config, current, force=True)
    if config.imu_set is not None:  # the device runs no IMU set: the configured file
        if pulled:
            messages.append(SetsNote(f"{where}: runs single-axis sets, not an IMU set; "
                                     f"using {config.imu_set}"))
        return files, messages + file_messages
    axes = list(files.axes)
    for i, ax in enumerate(axes):
        cset = pulled.get(ax.axis)
        if cset is None:
            messages += [m for m in file_messages if m.text.startswith(f"axis {ax.axis}:")]
            continue
        try:
            corrector = check_set(config, ax.axis, cset, where)
        except CanicalError as exc:
            messages.append(SetsNote(f"axis {ax.axis}: {exc}; using the coefficient file"))
            messages += [m for m in file_messages if m.text.startswith(f"axis {ax.axis}:")]
            continue
        old = current.axes[i]
        if old.corrector is not None and old.set_id == corrector.set_id:
            axes[i] = replace(old, source=SOURCE_DEVICE, stamp=file_stamp(ax.path),
                              version=versions.get(ax.axis))
            continue
        was = f"0x{old.set_id:08x}" if old.corrector else "none"
        messages.append(SetsNote(f"axis {ax.axis}: set 0x{corrector.set_id:08x} from {where} replaces {was}"))
        axes[i] = replace(ax, corrector=corrector, set_id=corrector.set_id, source=SOURCE_DEVICE,
                          reloads=old.reloads + (1 if old.corrector is not None else 0),
                          stamp=file_stamp(ax.path), version=versions.get(ax.axis))
    return build(tuple(axes)), messages


@dataclass(frozen=True)
class DeviceSets:
    """What a device runs, as pulled: single-axis sets, or an IMU set, and its banks' signatures."""

    sets: dict[str, CoefficientSet]
    imu: ImuSet | None
    signatures: dict[str, bytes]


def device_versions(config: DaemonConfig, current: ActiveSets, pulled: DeviceSets,
                    where: str) -> dict[str, int | None]:
    """The signed version of each set a device runs (by axis, ``"imu"`` for an IMU set), verified
    against ``trust:`` as a file is: signed by a trusted key for its sensor over the bytes the device
    holds, and not older than the set it replaces; else one CanicalError line."""
    from canical.device.bank_payload import encode_set
    from canical.device.bank_signature import verify_pulled
    from canical.sets.coefficient_file import canonical_bytes
    from canical.sets.signing import check_not_older

    assert config.trust is not None
    keys = config.trust.keys
    running = {ax.axis: ax.version for ax in current.axes}
    if pulled.imu is not None:
        source = f"{where} IMU set"
        record = verify_pulled(pulled.signatures.get("imu", b""), canonical_bytes(pulled.imu.to_dict()),
                               pulled.imu.sensor_id, keys, source)
        check_not_older(record, running.get("x"), source)
        return {"imu": record.version}
    versions: dict[str, int | None] = {}
    for axis, cset in pulled.sets.items():
        source = f"{where} axis {axis}"
        record = verify_pulled(pulled.signatures.get(axis, b""), encode_set(cset)[0], cset.sensor_id, keys,
                               source)
        check_not_older(record, running.get(axis), source)
        versions[axis] = record.version
    return versions


def _device_imu(config: DaemonConfig, current: ActiveSets, imu: ImuSet,
                where: str, version: int | None = None) -> tuple[ActiveSets, list[SetsNote]]:
    """The IMU set a device runs, each axis checked as a file's is (the coupling was, on pulling)."""
    if tuple(a.axis for a in config.axes) != AXES:
        raise CanicalError(f"{where}: runs an IMU set; the configuration has axes "
                           f"{', '.join(a.axis for a in config.axes)}, not x, y and z")
    correctors = [check_set(config, axis, cset, f"{where}: axes.{axis}")
                  for axis, cset in zip(AXES, imu.axes, strict=True)]
    imu_id = imu_set_crc(imu)
    axes = _imu_axes(current, correctors, SOURCE_DEVICE, tuple(file_stamp(a.path) for a in current.axes),
                     version)
    if current.coupling is not None and current.combined_id == imu_id:
        return build(axes, imu), []
    was = f"0x{current.combined_id:08x}" if current.complete else "none"
    return build(axes, imu), [SetsNote(f"imu set 0x{imu_id:08x} from {where} replaces {was}")]


def reload(config: DaemonConfig, current: ActiveSets, *, force: bool) -> tuple[ActiveSets, list[SetsNote]]:
    """New sets for the files that changed (all of them with ``force``), and what happened.

    The result is either ``current`` itself (nothing changed) or a new value built from
    fully validated sets; a file that fails validation leaves its axis as it was.
    """
    if config.imu_set is not None:
        return reload_imu(config, current, config.imu_set, force=force)
    messages: list[SetsNote] = []
    axes = list(current.axes)
    changed = False
    for i, ax in enumerate(axes):
        if ax.path is None:
            continue
        stamp = file_stamp(ax.path)
        if not force and stamp == ax.stamp:
            continue
        keep = "keeping set " + (f"0x{ax.set_id:08x}" if ax.corrector else "none")
        try:
            corrector, origin = load_axis_origin(config, ax.axis, ax.path, ax.version)
        except CanicalError as exc:
            messages.append(SetsNote(f"axis {ax.axis}: {exc}; {keep}", refused=True))
            axes[i] = replace(ax, stamp=stamp)
            changed = changed or stamp != ax.stamp
            continue
        if origin.warning is not None:
            messages.append(SetsNote(f"axis {ax.axis}: {origin.warning}"))
        if ax.corrector is not None and corrector.set_id == ax.set_id:
            # same content: keep the running corrector and its state (a re-signed set: its version)
            axes[i] = replace(ax, stamp=stamp, version=origin.version)
            changed = changed or stamp != ax.stamp or origin.version != ax.version
            continue
        old = f"0x{ax.set_id:08x}" if ax.corrector else "none"
        messages.append(SetsNote(f"axis {ax.axis}: set 0x{corrector.set_id:08x} from {ax.path} "
                                 f"replaces {old}"))
        axes[i] = replace(
            ax,
            corrector=corrector,
            set_id=corrector.set_id,
            source=SOURCE_FILE,
            reloads=ax.reloads + (1 if ax.corrector is not None else 0),
            stamp=stamp,
            version=origin.version,
        )
        changed = True
    if not changed:
        return current, messages
    return build(tuple(axes)), messages



def load_imu(config: DaemonConfig, path: Path) -> tuple[ImuSet, tuple[Corrector, ...]]:
    """Load an IMU set and validate each of its axes as a single-axis set is validated (the
    coupling is checked by the loader); any defect is one CanicalError line."""
    imu, correctors, _ = load_imu_origin(config, path, None)
    return imu, correctors


def load_imu_origin(config: DaemonConfig, path: Path,
                    running: int | None) -> tuple[ImuSet, tuple[Corrector, ...], Origin]:
    """:func:`load_imu`, and the signature verified against ``trust:`` (``running``: the version
    of the IMU set it would replace)."""
    imu, signed = signed_file.load_imu(path)
    origin = verify_origin(config, signed, running, str(path))
    configured = tuple(a.axis for a in config.axes)
    if configured != AXES:
        raise CanicalError(f"{path}: an IMU set corrects axes x, y and z; the configuration has "
                           f"{', '.join(configured)}")
    return imu, tuple(check_set(config, axis, cset, f"{path}: axes.{axis}")
                      for axis, cset in zip(AXES, imu.axes, strict=True)), origin


def reload_imu(config: DaemonConfig, current: ActiveSets, path: Path, *,
               force: bool) -> tuple[ActiveSets, list[SetsNote]]:
    """:func:`reload` for an IMU set: the three axes and the coupling replaced together, or not at all.

    An axis whose model is the one running keeps its corrector (and the state of its terms)."""
    stamp = file_stamp(path)
    if not force and all(ax.stamp == stamp for ax in current.axes):
        return current, []
    restamped = tuple(replace(ax, stamp=stamp) for ax in current.axes)
    keep = "keeping " + (f"IMU set 0x{current.combined_id:08x}" if current.complete else "no set")
    try:
        imu, correctors, origin = load_imu_origin(config, path, current.axes[0].version)
    except CanicalError as exc:
        same_file = all(ax.stamp == stamp for ax in current.axes)
        note = SetsNote(f"imu set: {exc}; {keep}", refused=True)
        return current if same_file else replace(current, axes=restamped), [note]
    warned = [] if origin.warning is None else [SetsNote(f"imu set: {origin.warning}")]
    imu_id = imu_set_crc(imu)
    if current.complete and current.coupling is not None and imu_id == current.combined_id:
        return replace(current, axes=tuple(replace(a, version=origin.version) for a in restamped)), warned
    axes = _imu_axes(current, correctors, SOURCE_FILE, (stamp,) * len(current.axes), origin.version)
    was = f"0x{current.combined_id:08x}" if current.complete else "none"
    return build(axes, imu), [*warned, SetsNote(f"imu set 0x{imu_id:08x} from {path} replaces {was}")]


def _imu_axes(current: ActiveSets, correctors: list[Corrector] | tuple[Corrector, ...], source: int,
              stamps: tuple[FileStamp, ...], version: int | None = None) -> tuple[AxisSet, ...]:
    """An IMU set's three axes from ``correctors``: an axis whose model is the one running keeps
    its corrector (and the state of its terms); another counts a reload."""
    axes = []
    for old, corrector, stamp in zip(current.axes, correctors, stamps, strict=True):
        same = old.corrector is not None and old.set_id == corrector.set_id
        axes.append(replace(old, corrector=old.corrector if same else corrector, set_id=corrector.set_id,
                            source=source, stamp=stamp, version=version,
                            reloads=old.reloads + (1 if old.corrector is not None and not same else 0)))
    return tuple(axes)
