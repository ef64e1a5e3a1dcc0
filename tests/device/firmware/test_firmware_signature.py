"""The firmware's C library checks a bank's signature before activation as the emulated IMU does:
built here against the distribution's libsodium (libsodium23, its Ed25519 verification given to
ce_signature_check as a function, as an MCU gives its vendor's), every case of
tests/support/signed_banks.py gets the same verdict from C and from the emulated IMU."""

from __future__ import annotations

import ctypes
import hashlib
import shutil
import subprocess
from pathlib import Path

import pytest
from support.firmware_build import CODES, FIRMWARE
from support.firmware_cases import CHANNELS, SERIAL
from support.imu_fixtures import imu_set, imu_triad_set
from support.signed_banks import (
    COUNTER,
    LAB_PUBLIC,
    REFUSAL_OF_CODE,
    VERSION,
    axis_cases,
    device_verdict,
    device_verdict3,
    imu_cases,
)

from canical.device.firmware_eval import CFLAGS, ERROR_NAMES, Library, make_device

LIBSODIUM = Path("/usr/lib/x86_64-linux-gnu/libsodium.so.23")
SHIM = Path(__file__).with_name("sodium_shim.c")
KEY_ID = hashlib.sha256(LAB_PUBLIC).digest()[:8]


@pytest.fixture(scope="module")
def signed_lib(tmp_path_factory) -> Library:
    """canical_eval.c and the libsodium shim in one library, linked with libsodium.so.23."""
    if not LIBSODIUM.is_file():
        pytest.skip(f"{LIBSODIUM} missing: install the distribution's libsodium23 to test the C check")
    if shutil.which("cc") is None:
        pytest.skip("no C compiler (cc)")
    out = tmp_path_factory.mktemp("signed") / "libcanical_signed.so"
    cmd = ["cc", *CFLAGS, "-I", str(FIRMWARE), "-o", str(out), str(SHIM), str(FIRMWARE / "canical_eval.c"),
           str(LIBSODIUM)]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    lib = Library(out)
    u8 = ctypes.c_char_p
    common = [u8, u8, ctypes.c_uint64, u8, ctypes.c_uint32, u8, ctypes.c_uint32]
    lib.lib.shim_check.argtypes = [*common, ctypes.c_uint32, ctypes.POINTER(ctypes.c_uint64)]
    lib.lib.shim_check3.argtypes = [*common, ctypes.c_char_p * 3, ctypes.c_uint32 * 3, ctypes.c_uint32,
                                    ctypes.POINTER(ctypes.c_uint64)]
    assert lib.lib.shim_init() >= 0
    return lib


def c_verdict(lib: Library, case) -> tuple[str, int]:
    """The C library's code for an axis case (ce_load, then ce_signature_check) and the version."""
    buffer = ctypes.create_string_buffer(lib.set_size)
    device = make_device(SERIAL, "z", 50.0, CHANNELS)
    code = lib.lib.ce_load(buffer, case.content, len(case.content), case.crc, ctypes.byref(device))
    version = ctypes.c_uint64(0)
    if code == 0:
        code = lib.lib.shim_check(LAB_PUBLIC, KEY_ID, COUNTER, case.signature, len(case.signature),
                                  case.content, len(case.content), SERIAL, ctypes.byref(version))
    return ERROR_NAMES.get(code, "CE_OK"), version.value


def c_verdict3(lib: Library, case) -> tuple[str, int]:
    """The C library's code for an IMU set case (ce_coupling_load, then ce_signature_check3)."""
    buffer = ctypes.create_string_buffer(lib.coupling_size)
    device = make_device(SERIAL, "x", 0.0, ())
    axes = (ctypes.c_char_p * 3)(*case.axes)
    lengths = (ctypes.c_uint32 * 3)(*map(len, case.axes))
    code = lib.lib.ce_coupling_load(buffer, case.coupling, len(case.coupling), case.coupling_crc,
                                    case.imu_set_id, axes, lengths, ctypes.byref(device))
    version = ctypes.c_uint64(0)
    if code == 0:
        code = lib.lib.shim_check3(LAB_PUBLIC, KEY_ID, COUNTER, case.signature, len(case.signature),
                                   case.coupling, len(case.coupling), axes, lengths, SERIAL,
                                   ctypes.byref(version))
    return ERROR_NAMES.get(code, "CE_OK"), version.value


@pytest.mark.parametrize("case", axis_cases(imu_set("z")), ids=lambda c: c.name)
def test_c_and_the_emulated_imu_agree_on_an_axis_bank(signed_lib: Library, case) -> None:
    code, version = c_verdict(signed_lib, case)
    refusal = device_verdict(case)
    if case.refusal is None:
        assert (code, version, refusal) == ("CE_OK", VERSION, None)
        return
    assert code in REFUSAL_OF_CODE, code
    assert refusal is not None and REFUSAL_OF_CODE[code] in refusal and case.refusal in refusal


@pytest.mark.parametrize("case", imu_cases(imu_triad_set(0)), ids=lambda c: c.name)
def test_c_and_the_emulated_imu_agree_on_an_imu_set(signed_lib: Library, case) -> None:
    code, version = c_verdict3(signed_lib, case)
    refusal = device_verdict3(case)
    if case.refusal is None:
        assert (code, version, refusal) == ("CE_OK", VERSION, None)
        return
    assert code in REFUSAL_OF_CODE, code
    assert refusal is not None and REFUSAL_OF_CODE[code] in refusal and case.refusal in refusal


def test_a_scratch_too_small_is_a_refusal_not_an_overflow(signed_lib: Library) -> None:
    """The message is built in the caller's buffer: one too small is CE_ERR_LIMIT, nothing written past it."""
    case = axis_cases(imu_set("z"))[-1]

    def verify(_ctx, _sig, _msg, _len, _pk) -> int:
        return 0

    fn = ctypes.CFUNCTYPE(ctypes.c_int, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_void_p, ctypes.c_uint32,
                          ctypes.c_void_p)(verify)

    class Trust(ctypes.Structure):
        _fields_ = [("public_key", ctypes.c_char_p), ("key_id", ctypes.c_char_p),
                    ("counter", ctypes.c_uint64), ("verify", type(fn)), ("context", ctypes.c_void_p),
                    ("scratch", ctypes.c_void_p), ("scratch_size", ctypes.c_uint32)]

    scratch = ctypes.create_string_buffer(len(case.content) + 16)  # the header does not fit too
    room = len(case.content) + 8
    trust = Trust(LAB_PUBLIC, KEY_ID, 0, fn, None, ctypes.cast(scratch, ctypes.c_void_p), room)
    version = ctypes.c_uint64(0)
    check = signed_lib.lib.ce_signature_check
    check.argtypes = [ctypes.POINTER(Trust), ctypes.c_char_p, ctypes.c_uint32, ctypes.c_char_p,
                      ctypes.c_uint32, ctypes.c_uint32, ctypes.POINTER(ctypes.c_uint64)]
    code = check(ctypes.byref(trust), case.signature, len(case.signature), case.content, len(case.content),
                 SERIAL, ctypes.byref(version))
    assert code == CODES["CE_ERR_LIMIT"] and scratch.raw[-8:] == bytes(8)
