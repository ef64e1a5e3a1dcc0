"""The firmware evaluator with an IMU set: the coupling loaded from the banks' bytes under the
rules of canical.sets.imu_set.check_coupling and the device's (it must belong to the three axis
banks), and a three-axis sample corrected as `canical apply imu.yaml` (ImuCorrector) does."""

from __future__ import annotations

import ctypes
import zlib

import numpy as np
import pytest
from support.firmware_build import CODES, TOLERANCE_DPS
from support.firmware_cases import SERIAL, imu_every_term_set, imu_stream
from support.imu_fixtures import imu_triad_set

from canical.device.bank_payload import CouplingPayload, encode_coupling, encode_set
from canical.device.firmware_eval import FirmwareImuCorrector, FirmwareRefusal, Library, make_device
from canical.errors import CanicalError
from canical.sets.coefficient_file import canonical_bytes
from canical.sets.imu_corrector import ImuCorrector
from canical.sets.imu_set import check_coupling

SEEDS = (0, 1, 2)
#: In the suite; the benchmark (tests/benchmarks/bench_firmware_eval.py) runs 10^6 samples.
N = 100_000


def imu_case(kind: str, seed: int):
    return imu_triad_set(seed) if kind == "triad" else imu_every_term_set(seed)


@pytest.mark.parametrize("kind", ["triad", "every term"])
@pytest.mark.parametrize("seed", SEEDS)
def test_three_axis_sample_equals_apply(lib: Library, kind: str, seed: int) -> None:
    imu = imu_case(kind, seed)
    raw, inputs = imu_stream(imu, N, seed)
    expected, flags = ImuCorrector(imu).correct(raw, inputs)
    rates, oos = FirmwareImuCorrector(imu, lib=lib).correct(raw, inputs)
    worst = float(np.max(np.abs(rates - expected)))
    assert worst <= TOLERANCE_DPS, f"{kind} seed {seed}: largest difference {worst:.2e} deg/s"
    assert np.array_equal(oos, flags) and 0 < oos.mean() < 0.5
    per_axis, _ = ImuCorrector(imu).per_axis(raw, inputs)
    assert np.max(np.abs(expected - per_axis)) > 100 * TOLERANCE_DPS  # the coupling is felt


@pytest.mark.parametrize("seed", SEEDS)
def test_without_coupling_the_three_sets_run_alone(lib: Library, seed: int) -> None:
    imu = imu_triad_set(seed)
    raw, inputs = imu_stream(imu, 20_000, seed)
    per_axis, flags = ImuCorrector(imu).per_axis(raw, inputs)
    rates, oos = FirmwareImuCorrector(imu, coupling=False, lib=lib).correct(raw, inputs)
    assert float(np.max(np.abs(rates - per_axis))) <= TOLERANCE_DPS and np.array_equal(oos, flags)


def coupling_code(lib: Library, imu, payload: CouplingPayload | None = None, *, axes=None,
                  serial: int = SERIAL) -> int:
    """ce_coupling_load's verdict on a coupling bank with the axis banks of ``axes`` (default: imu's)."""
    p = payload or encode_coupling(imu)
    contents = [encode_set(c)[0] for c in (axes or imu).axes]
    buffer = ctypes.create_string_buffer(lib.coupling_size)
    device = make_device(serial, "x", 0.0, ())
    lengths = (ctypes.c_uint32 * 3)(*map(len, contents))
    return lib.lib.ce_coupling_load(buffer, p.content, len(p.content), p.crc, p.imu_set_id,
                                    (ctypes.c_char_p * 3)(*contents), lengths, ctypes.byref(device))


def with_matrix(imu, matrix, **extra) -> CouplingPayload:
    envelope = {k: v for k, v in imu.to_dict().items() if k != "axes"}
    envelope["coupling"] = {**envelope["coupling"], "matrix": matrix}
    envelope.update(extra)
    content = canonical_bytes(envelope)
    whole = {**envelope, "axes": {c.axis: c.to_dict() for c in imu.axes}}
    return CouplingPayload(content, zlib.crc32(content), zlib.crc32(canonical_bytes(whole)))


def test_the_imu_set_id_is_computed_from_the_banks_bytes(lib: Library) -> None:
    for seed in SEEDS:
        assert coupling_code(lib, imu_triad_set(seed)) == 0


@pytest.mark.parametrize(("case", "code"), [
    ("off-diagonal 12 %", "CE_ERR_COUPLING"),
    ("singular", "CE_ERR_COUPLING"),
    ("condition 2000", "CE_ERR_COUPLING"),
    ("diagonal 1e308", "CE_ERR_COUPLING"),
    ("diagonal -1", "CE_ERR_COUPLING"),
    ("diagonal 2e-3", "CE_ERR_COUPLING"),
    ("another IMU set's axes", "CE_ERR_IMU_SET"),
    ("declared id off by one bit", "CE_ERR_IMU_SET"),
    ("another sensor", "CE_ERR_SENSOR"),
    ("CRC", "CE_ERR_CRC"),
    ("axes inside", "CE_ERR_FIELD"),
    ("a row of two", "CE_ERR_FIELD"),
])
def test_refusals(lib: Library, case: str, code: str) -> None:
    imu = imu_triad_set(0)
    good = encode_coupling(imu)
    eye = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]
    payloads = {
        "off-diagonal 12 %": lambda: with_matrix(imu, [[1.0, 0.0, 0.0], [0.0, 1.0, -0.12], [0.0, 0.0, 1.0]]),
        "singular": lambda: with_matrix(imu, [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 0.0]]),
        "condition 2000": lambda: with_matrix(imu, [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 5e-4]]),
        "diagonal 1e308": lambda: with_matrix(imu, [[1e308, 0.0, 0.0], [0.0, 1e308, 0.0], [0.0, 0.0, 1e308]]),
        "diagonal -1": lambda: with_matrix(imu, [[-1.0, 0.0, 0.0], [0.0, -1.0, 0.0], [0.0, 0.0, -1.0]]),
        "diagonal 2e-3": lambda: with_matrix(imu, [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 2e-3]]),
        "declared id off by one bit": lambda: CouplingPayload(good.content, good.crc, good.imu_set_id ^ 1),
        "CRC": lambda: CouplingPayload(good.content, good.crc ^ 1, good.imu_set_id),
        "axes inside": lambda: with_matrix(imu, eye, axes={}),
        "a row of two": lambda: with_matrix(imu, [[1.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]]),
    }
    payload = payloads[case]() if case in payloads else None
    axes = imu_triad_set(1) if case == "another IMU set's axes" else None
    serial = SERIAL + 1 if case == "another sensor" else SERIAL
    assert coupling_code(lib, imu, payload, axes=axes, serial=serial) == CODES[code]


def test_the_matrix_rules_are_check_couplings(lib: Library) -> None:
    """Random matrices about the limits (off-diagonal terms to 11 %, diagonal terms 0.44 to 2.3):
    the C library and canical.sets.imu_set.check_coupling give the same verdict on every one."""
    imu = imu_triad_set(0)
    rng = np.random.default_rng(7)
    verdicts = {True: 0, False: 0}
    for _ in range(400):
        m = np.diag(10.0 ** rng.uniform(-0.36, 0.36, 3)) + (1 - np.eye(3)) * rng.uniform(-0.11, 0.11, (3, 3))
        try:
            check_coupling(m, "m")
            python_ok = True
        except CanicalError:
            python_ok = False
        c_ok = coupling_code(lib, imu, with_matrix(imu, m.tolist())) == 0
        assert c_ok == python_ok, m
        verdicts[python_ok] += 1
    assert min(verdicts.values()) > 40  # both verdicts well represented


def test_sets_that_are_not_the_couplings_are_refused_per_sample(lib: Library) -> None:
    a, b = FirmwareImuCorrector(imu_triad_set(0), lib=lib), FirmwareImuCorrector(imu_triad_set(1), lib=lib)
    raw = np.zeros(3, dtype=np.float32)
    rate = np.zeros(3, dtype=np.float32)
    oos = np.zeros(3, dtype=np.uint8)
    f32p, u8p = ctypes.POINTER(ctypes.c_float), ctypes.POINTER(ctypes.c_uint8)
    code = lib.lib.ce_eval3_block(b._sets, a._coupling, 1, raw.ctypes.data_as(f32p), None, None, 0,
                                  rate.ctypes.data_as(f32p), oos.ctypes.data_as(u8p))
    assert code == CODES["CE_ERR_IMU_SET"]
    with pytest.raises(FirmwareRefusal, match="CE_ERR_SENSOR"):
        FirmwareImuCorrector(imu_triad_set(0), serial=SERIAL + 1, lib=lib)


def test_fuzz_coupling_banks_under_sanitizers(sanitized_driver, tmp_path) -> None:
    """30,000 random mutations of a coupling bank (CRC recomputed for most), loaded with its three
    axis banks: no sanitizer report, the bank as given accepted, and the C library's verdict
    canical's own (canical.device.bank_payload: decode_coupling, then join_imu_set)."""
    import struct
    import subprocess

    from canical.device.bank_payload import decode_coupling, join_imu_set

    imu = imu_triad_set(0)
    p = encode_coupling(imu)
    records = tmp_path / "records.bin"
    banks = [*(encode_set(c) for c in imu.axes), (p.content, p.crc)]
    records.write_bytes(b"".join(struct.pack("<II", len(c), crc) + c for c, crc in banks))
    n = 30_000
    done = subprocess.run(
        [str(sanitized_driver), "coupling", str(records), str(n), "77", str(p.imu_set_id), str(SERIAL), "x",
         "0", "temp_c", "supply_v"],
        capture_output=True, text=True, check=False, timeout=600,
        env={"ASAN_OPTIONS": "abort_on_error=0:exitcode=99", "UBSAN_OPTIONS": "exitcode=99",
             "CE_SAMPLE_EVERY": "10"},
    )
    assert done.returncode == 0 and "Sanitizer" not in done.stderr and "runtime error" not in done.stderr, (
        done.stderr[-3000:])
    *lines, summary = done.stdout.splitlines()
    assert summary.startswith(f"cases {n} accepted ")
    rows = [(int(code), int(crc, 16), bytes.fromhex(hexed)) for code, crc, hexed in
            ([*ln.split(" "), ""][:3] for ln in lines)]
    assert rows[0] == (0, p.crc, p.content)
    refused = [r for r in rows if r[0] != 0]
    assert len(refused) > 1000

    def python_accepts(content: bytes, crc: int) -> bool:
        try:
            join_imu_set(decode_coupling(content, crc, "bank"), imu.axes, p.imu_set_id, "bank")
        except CanicalError:
            return False
        return True

    for code, crc, content in rows:
        assert python_accepts(content, crc) == (code == 0), (code, content)
