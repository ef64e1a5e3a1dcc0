"""The firmware's C evaluator (``firmware/canical_eval.c``) from Python, through ctypes.

The emulated IMU corrects its samples with the very C code a sensor's MCU would run,
so the bus tests exercise the firmware, not a Python twin of it. The library is
compiled from the sources shipped in the package (``canical/data/canical_eval.c``,
a link to ``firmware/``) with the system C compiler on first use, into a cache
directory keyed by the sources' hash; where no compiler exists (or
``CANICAL_FIRMWARE=python``) :func:`corrector_for` logs one line and returns the
Python :class:`~canical.sets.corrector.Corrector`, so nothing else changes.

Time reaches the firmware as a millisecond counter (``time_ms``), the way a device
keeps it; ``time_s`` inputs are rounded to the millisecond on the way in.
"""

from __future__ import annotations

import ctypes
import functools
import hashlib
import logging
import os
import shutil
import subprocess
import tempfile
from collections.abc import Mapping, Sequence
from importlib import resources
from pathlib import Path

import numpy as np

from canical.device.bank_payload import encode_coupling, encode_set
from canical.errors import CanicalError
from canical.sets.coefficients import CoefficientSet
from canical.sets.corrector import Corrector
from canical.sets.imu_corrector import ImuCorrector
from canical.sets.imu_set import AXES, ImuSet
from canical.sets.terms import TIME_INPUT

log = logging.getLogger("canical.firmware")

SOURCES = ("canical_eval.c", "canical_eval.h")
CFLAGS = ("-std=c99", "-Wall", "-Wextra", "-Werror", "-O2", "-fPIC", "-shared")
ERROR_NAMES = {
    -1: "CE_ERR_ARG",
    -2: "CE_ERR_CRC",
    -3: "CE_ERR_SYNTAX",
    -4: "CE_ERR_NOT_CANONICAL",
    -5: "CE_ERR_SCHEMA",
    -6: "CE_ERR_FIELD",
    -7: "CE_ERR_MODEL_KIND",
    -8: "CE_ERR_TERM_KIND",
    -9: "CE_ERR_LIMIT",
    -10: "CE_ERR_SENSOR",
    -11: "CE_ERR_AXIS",
    -12: "CE_ERR_SPAN",
    -13: "CE_ERR_INPUT",
    -14: "CE_ERR_COUPLING",
    -15: "CE_ERR_IMU_SET",
    -16: "CE_ERR_UNSIGNED",
    -17: "CE_ERR_SIGNATURE_FORMAT",
    -18: "CE_ERR_KEY",
    -19: "CE_ERR_SIGNATURE",
    -20: "CE_ERR_ROLLBACK",
}


class Device(ctypes.Structure):
    _fields_ = [
        ("serial", ctypes.c_uint32),
        ("axis", ctypes.c_char),
        ("rated_range_dps", ctypes.c_float),
        ("inputs", ctypes.POINTER(ctypes.c_char_p)),
        ("n_inputs", ctypes.c_uint8),
    ]


class Sample(ctypes.Structure):
    _fields_ = [
        ("raw", ctypes.c_float),
        ("time_ms", ctypes.c_uint32),
        ("inputs", ctypes.POINTER(ctypes.c_float)),
    ]


class FirmwareRefusal(CanicalError):
    """The C library refused a set: ``code`` is its CE_ERR_* value."""

    def __init__(self, message: str, code: int) -> None:
        super().__init__(message)
        self.code = code


def source_dir() -> Path:
    """Where the C sources are: inside the package (links to ``firmware/`` in a checkout)."""
    return Path(str(resources.files("canical") / "data"))


def compile_library(
    output: Path, *, compiler: str | None = None, extra_flags: Sequence[str] = (), sources: Path | None = None
) -> None:
    """Compile the evaluator as a shared library (warnings are errors); CanicalError if it fails."""
    cc = compiler or os.environ.get("CC", "cc")
    src = (sources or source_dir()) / "canical_eval.c"
    cmd = [cc, *CFLAGS, *extra_flags, "-o", str(output), str(src)]
    try:
        done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, check=False)
    except (OSError, subprocess.TimeoutExpired) as exc:
        raise CanicalError(f"cannot run the C compiler {cc!r} ({exc})") from None
    if done.returncode != 0:
        first = (done.stderr.strip().splitlines() or ["no message"])[0]
        raise CanicalError(f"{' '.join(cmd)} failed: {first}")


def _cache_dir() -> Path:
    base = os.environ.get("XDG_CACHE_HOME") or str(Path.home() / ".cache")
    return Path(base) / "canical"


@functools.cache
def library_path() -> Path:
    """The compiled library for the shipped sources, built once per source version (atomically)."""
    digest = hashlib.sha256()
    for name in SOURCES:
        digest.update((source_dir() / name).read_bytes())
    digest.update(" ".join(CFLAGS).encode())
    name = f"libcanical_eval-{digest.hexdigest()[:16]}.so"
    for folder in (_cache_dir(), Path(tempfile.gettempdir()) / f"canical-{os.getuid()}"):
        if (folder / name).is_file():
            return folder / name
    if shutil.which(os.environ.get("CC", "cc")) is None:
        raise CanicalError("no C compiler (cc) on this machine")
    target = _cache_dir() / name
    try:
        target.parent.mkdir(parents=True, exist_ok=True)
    except OSError:  # no writable home (a service user): a private folder under /tmp
        target = Path(tempfile.gettempdir()) / f"canical-{os.getuid()}" / name
        target.parent.mkdir(mode=0o700, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=".build-", suffix=".so", dir=target.parent)
    os.close(fd)
    try:
        compile_library(Path(tmp))
        os.replace(tmp, target)
    finally:
        if os.path.exists(tmp):
            os.unlink(tmp)
    return target


class Library:
    """The C functions with their signatures."""

    def __init__(self, path: Path) -> None:
        lib = ctypes.CDLL(str(path))
        u8p = ctypes.POINTER(ctypes.c_uint8)
        f32p = ctypes.POINTER(ctypes.c_float)
        lib.ce_crc32.argtypes = [ctypes.c_char_p, ctypes.c_uint32]
        lib.ce_crc32.restype = ctypes.c_uint32
        lib.ce_load.argtypes = [
            ctypes.c_void_p,
            ctypes.c_char_p,
            ctypes.c_uint32,
            ctypes.c_uint32,
            ctypes.POINTER(Device),
        ]
        lib.ce_load.restype = ctypes.c_int
        lib.ce_reset.argtypes = [ctypes.c_void_p]
        lib.ce_reset.restype = None
        lib.ce_eval.argtypes = [ctypes.c_void_p, ctypes.POINTER(Sample), f32p]
        lib.ce_eval.restype = ctypes.c_int
        lib.ce_eval_block.argtypes = [
            ctypes.c_void_p,
            ctypes.c_uint32,
            f32p,
            ctypes.POINTER(ctypes.c_uint32),
            f32p,
            ctypes.c_uint8,
            f32p,
            u8p,
        ]
        lib.ce_eval_block.restype = ctypes.c_int
        lib.ce_strerror.argtypes = [ctypes.c_int]
        lib.ce_strerror.restype = ctypes.c_char_p
        lib.ce_sizeof_set.argtypes = []
        lib.ce_sizeof_set.restype = ctypes.c_uint32
        lib.ce_error_offset.argtypes = [ctypes.c_void_p]
        lib.ce_error_offset.restype = ctypes.c_uint32
        lib.ce_sizeof_fixed.argtypes = []
        lib.ce_sizeof_fixed.restype = ctypes.c_uint32
        lib.ce_fixed_from.argtypes = [ctypes.c_void_p, ctypes.c_void_p]
        lib.ce_fixed_from.restype = ctypes.c_int
        lib.ce_fixed_eval.argtypes = [ctypes.c_void_p, ctypes.c_int32, ctypes.POINTER(ctypes.c_int32)]
        lib.ce_fixed_eval.restype = ctypes.c_int
        sets3 = ctypes.c_void_p * 3
        lib.ce_coupling_load.argtypes = [
            ctypes.c_void_p,
            ctypes.c_char_p,
            ctypes.c_uint32,
            ctypes.c_uint32,
            ctypes.c_uint32,
            ctypes.c_char_p * 3,
            ctypes.c_uint32 * 3,
            ctypes.POINTER(Device),
        ]
        lib.ce_coupling_load.restype = ctypes.c_int
        lib.ce_eval3_block.argtypes = [
            sets3,
            ctypes.c_void_p,
            ctypes.c_uint32,
            f32p,
            ctypes.POINTER(ctypes.c_uint32),
            f32p,
            ctypes.c_uint8,
            f32p,
            u8p,
        ]
        lib.ce_eval3_block.restype = ctypes.c_int
        lib.ce_sizeof_coupling.argtypes = []
        lib.ce_sizeof_coupling.restype = ctypes.c_uint32
        self.lib = lib
        self.coupling_size = int(lib.ce_sizeof_coupling())
        self.set_size = int(lib.ce_sizeof_set())
        self.fixed_size = int(lib.ce_sizeof_fixed())

    def strerror(self, code: int) -> str:
        return str(self.lib.ce_strerror(code).decode())


@functools.cache
def library() -> Library:
    """The loaded library; CanicalError when it cannot be built or loaded here."""
    if os.environ.get("CANICAL_FIRMWARE", "").lower() == "python":
        raise CanicalError("CANICAL_FIRMWARE=python")
    path = library_path()
    try:
        return Library(path)
    except OSError as exc:
        raise CanicalError(f"cannot load {path} ({exc})") from None


def make_device(serial: int, axis: str, rated_range_dps: float, inputs: Sequence[str]) -> Device:
    names = (ctypes.c_char_p * max(1, len(inputs)))(*[n.encode() for n in inputs])
    device = Device(int(serial), axis.encode()[:1], float(rated_range_dps), names, len(inputs))
    device._names = names  # keep the strings alive with the struct
    return device


class FirmwareCorrector:
    """A coefficient set loaded into the C evaluator: the :class:`Corrector` interface, in C.

    ``content``/``crc`` are the bank bytes (the set's canonical JSON) the device validates;
    the set must be admitted for ``serial``, ``axis`` and ``rated_range_dps`` (0: no span check).
    """

    def __init__(
        self,
        cset: CoefficientSet,
        *,
        serial: int | None = None,
        axis: str | None = None,
        rated_range_dps: float = 0.0,
        channels: Sequence[str] | None = None,
        lib: Library | None = None,
    ) -> None:
        """``channels``: the run-time channels the device offers, in sample order (default: the
        set's own); a superset lets three axes' sets share one sample's inputs."""
        self.lib = lib or library()
        self.cset = cset
        content, crc = encode_set(cset)
        self.set_id = crc
        reference = Corrector(cset)  # names the inputs exactly as the Python evaluator does
        self.required_inputs = reference.required_inputs
        own = tuple(n for n in self.required_inputs if n != TIME_INPUT)
        self.channels = own if channels is None else tuple(channels)
        if serial is None:
            serial = int(cset.sensor_id) if cset.sensor_id.isdigit() else 0
        self.device = make_device(serial, axis or cset.axis, rated_range_dps, self.channels)
        self._set = ctypes.create_string_buffer(self.lib.set_size)
        code = self.lib.lib.ce_load(self._set, content, len(content), crc, ctypes.byref(self.device))
        if code != 0:
            at = self.lib.lib.ce_error_offset(self._set)
            raise FirmwareRefusal(
                f"set 0x{crc:08x}: the firmware evaluator refuses it: {self.lib.strerror(code)} "
                f"({ERROR_NAMES.get(code, code)} at byte {at})",
                code,
            )
        self._inputs = (ctypes.c_float * max(1, len(self.channels)))()
        self._sample = Sample(0.0, 0, self._inputs)
        self._rate = ctypes.c_float()

    def reset(self) -> None:
        self.lib.lib.ce_reset(self._set)

    def correct_one(self, raw: float, inputs: Mapping[str, float] | None = None) -> tuple[float, bool]:
        inputs = inputs or {}
        for i, name in enumerate(self.channels):
            self._inputs[i] = float(inputs[name])
        self._sample.raw = float(raw)
        self._sample.time_ms = time_ms(float(inputs[TIME_INPUT])) if TIME_INPUT in inputs else 0
        code = self.lib.lib.ce_eval(self._set, ctypes.byref(self._sample), ctypes.byref(self._rate))
        if code < 0:
            raise CanicalError(f"firmware evaluator: {self.lib.strerror(code)}")
        return float(self._rate.value), bool(code)

    def correct(
        self, raw: np.ndarray, inputs: Mapping[str, np.ndarray] | None = None
    ) -> tuple[np.ndarray, np.ndarray]:
        """A block in time order from a fresh state, like :meth:`Corrector.correct`."""
        inputs = inputs or {}
        missing = [n for n in self.required_inputs if n not in inputs]
        if missing:
            raise CanicalError(f"the coefficient set needs input(s) {', '.join(missing)}")
        raw32 = np.ascontiguousarray(raw, dtype=np.float32)
        n = len(raw32)
        t = np.zeros(n, dtype=np.uint32)
        if TIME_INPUT in inputs:
            t = np.ascontiguousarray(np.rint(np.asarray(inputs[TIME_INPUT], dtype=float) * 1000.0), np.uint32)
        chan = np.ascontiguousarray(
            np.column_stack([np.asarray(inputs[c], dtype=float) for c in self.channels])
            if self.channels
            else np.zeros((n, 0)),
            dtype=np.float32,
        )
        rate = np.empty(n, dtype=np.float32)
        oos = np.empty(n, dtype=np.uint8)
        f32p = ctypes.POINTER(ctypes.c_float)
        self.reset()
        code = self.lib.lib.ce_eval_block(
            self._set,
            n,
            raw32.ctypes.data_as(f32p),
            t.ctypes.data_as(ctypes.POINTER(ctypes.c_uint32)),
            chan.ctypes.data_as(f32p) if self.channels else None,
            len(self.channels),
            rate.ctypes.data_as(f32p),
            oos.ctypes.data_as(ctypes.POINTER(ctypes.c_uint8)),
        )
        self.reset()
        if code < 0:
            raise CanicalError(f"firmware evaluator: {self.lib.strerror(code)}")
        return rate.astype(float), oos.astype(bool)


class FirmwareImuCorrector:
    """An IMU set in the C evaluator: its three sets and its coupling (``ce_coupling_load``), a
    three-axis sample at a time (``ce_eval3``); the :class:`ImuCorrector` interface, in C.

    The coupling is loaded from the very bytes the device holds (the axis banks and the coupling
    bank), so the C library checks that it belongs to the three sets, as the device does.
    ``coupling=False`` runs the three sets alone (identity: a device without a coupling).
    """

    def __init__(self, imu: ImuSet, *, serial: int | None = None, rated_range_dps: float = 0.0,
                 coupling: bool = True, lib: Library | None = None) -> None:
        self.lib = lib or library()
        self.imu = imu
        reference = ImuCorrector(imu)
        self.required_inputs = reference.required_inputs
        self.channels = tuple(n for n in self.required_inputs if n != TIME_INPUT)
        if serial is None:
            serial = int(imu.sensor_id) if imu.sensor_id.isdigit() else 0
        self.axes = tuple(
            FirmwareCorrector(cset, serial=serial, axis=axis, rated_range_dps=rated_range_dps,
                              channels=self.channels, lib=self.lib)
            for axis, cset in zip(AXES, imu.axes, strict=True)
        )
        self._sets = (ctypes.c_void_p * 3)(*(ctypes.addressof(a._set) for a in self.axes))
        payload = encode_coupling(imu)
        self.set_id = payload.imu_set_id
        self._coupling: ctypes.Array[ctypes.c_char] | None = None
        if coupling:
            contents = [encode_set(c)[0] for c in imu.axes]
            buffer = ctypes.create_string_buffer(self.lib.coupling_size)
            device = make_device(serial, "x", rated_range_dps, self.channels)
            code = self.lib.lib.ce_coupling_load(
                buffer, payload.content, len(payload.content), payload.crc, payload.imu_set_id,
                (ctypes.c_char_p * 3)(*contents), (ctypes.c_uint32 * 3)(*map(len, contents)),
                ctypes.byref(device),
            )
            if code != 0:
                raise FirmwareRefusal(
                    f"IMU set 0x{payload.imu_set_id:08x}: the firmware evaluator refuses its coupling: "
                    f"{self.lib.strerror(code)} ({ERROR_NAMES.get(code, code)})",
                    code,
                )
            self._coupling = buffer
        self._one = {k: np.zeros(3, dtype=np.float32) for k in ("raw", "rate")}

    def reset(self) -> None:
        for a in self.axes:
            a.reset()

    def _run(self, raw32: np.ndarray, t: np.ndarray, chan: np.ndarray | None
             ) -> tuple[np.ndarray, np.ndarray]:
        n = raw32.shape[0]
        rate = np.empty((n, 3), dtype=np.float32)
        oos = np.empty((n, 3), dtype=np.uint8)
        f32p = ctypes.POINTER(ctypes.c_float)
        code = self.lib.lib.ce_eval3_block(
            self._sets,
            self._coupling,
            n,
            raw32.ctypes.data_as(f32p),
            t.ctypes.data_as(ctypes.POINTER(ctypes.c_uint32)),
            chan.ctypes.data_as(f32p) if chan is not None else None,
            len(self.channels),
            rate.ctypes.data_as(f32p),
            oos.ctypes.data_as(ctypes.POINTER(ctypes.c_uint8)),
        )
        if code < 0:
            raise CanicalError(f"firmware evaluator: {self.lib.strerror(code)}")
        return rate, oos

    def correct_one(self, raw: Sequence[float], inputs: Mapping[str, float] | None = None
                    ) -> tuple[list[float], list[bool]]:
        """The next three-axis sample of the stream (the sets keep their state between calls)."""
        inputs = inputs or {}
        raw32 = np.asarray(raw, dtype=np.float32).reshape(1, 3)
        t = np.asarray([time_ms(float(inputs[TIME_INPUT])) if TIME_INPUT in inputs else 0], dtype=np.uint32)
        chan = np.asarray([[inputs[c] for c in self.channels]], dtype=np.float32) if self.channels else None
        rate, oos = self._run(raw32, t, chan)
        return [float(v) for v in rate[0]], [bool(v) for v in oos[0]]

    def correct(self, raw: np.ndarray, inputs: Mapping[str, np.ndarray] | None = None
                ) -> tuple[np.ndarray, np.ndarray]:
        """Raw (n, 3) → rates (n, 3) and out-of-span flags (n, 3), from a fresh state, like
        :meth:`ImuCorrector.correct`."""
        inputs = inputs or {}
        missing = [n for n in self.required_inputs if n not in inputs]
        if missing:
            raise CanicalError(f"the IMU set needs input(s) {', '.join(missing)}")
        raw32 = np.ascontiguousarray(np.asarray(raw, dtype=float).reshape(-1, 3), dtype=np.float32)
        n = raw32.shape[0]
        t = np.zeros(n, dtype=np.uint32)
        if TIME_INPUT in inputs:
            t = np.ascontiguousarray(np.rint(np.asarray(inputs[TIME_INPUT], dtype=float) * 1000.0), np.uint32)
        chan = None
        if self.channels:
            columns = [np.asarray(inputs[c], dtype=float) for c in self.channels]
            chan = np.ascontiguousarray(np.column_stack(columns), dtype=np.float32)
        self.reset()
        try:
            rate, oos = self._run(raw32, t, chan)
        finally:
            self.reset()
        return rate.astype(float), oos.astype(bool)


def time_ms(time_s: float) -> int:
    """A time in seconds as the device's millisecond counter (UNSIGNED32, wrapping)."""
    return round(time_s * 1000.0) & 0xFFFFFFFF


def corrector_for(
    cset: CoefficientSet, *, serial: int, axis: str, rated_range_dps: float = 0.0
) -> FirmwareCorrector | Corrector:
    """The C evaluator for a set the device accepted, or the Python one (logged) where the
    library cannot be built or does not evaluate this set (e.g. a term kind it predates)."""
    try:
        return FirmwareCorrector(cset, serial=serial, axis=axis, rated_range_dps=rated_range_dps)
    except CanicalError as exc:
        log.warning("axis %s: correcting in Python, not with the firmware evaluator: %s", axis, exc)
        return Corrector(cset)
