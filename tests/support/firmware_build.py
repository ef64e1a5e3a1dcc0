"""What the firmware evaluator's tests share: where its source is, the device it is loaded for,
and canical's own verdict on a bank to compare the C library's with."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from canical.device import firmware_eval
from canical.device.bank_payload import decode_set, encode_set
from canical.device.firmware_eval import Library
from canical.errors import CanicalError
from canical.sets.admission import DeviceLimits, admission_problem
from canical.sets.coefficients import CoefficientSet
from support.firmware_cases import (
    AXIS,
    CHANNELS,
    MODELS,
    SERIAL,
    TERMS,
    model_set,
    term_set,
)

FIRMWARE = Path(__file__).resolve().parents[2] / "firmware"
SANITIZE = (
    "-O1",
    "-g",
    "-fsanitize=address,undefined",
    "-fno-sanitize-recover=all",
    "-fno-omit-frame-pointer",
)
RATED = 50.0
CE_MAX_SEGMENTS = 16
N_SAMPLES = 1_000_000
TOLERANCE_DPS = 1e-4
EPS32 = 2.0**-24  # float32 unit roundoff: a float32 result is within EPS32 of its exact value, relatively
CODES = {v: k for k, v in firmware_eval.ERROR_NAMES.items()}

def seeds() -> list[tuple[bytes, int]]:
    """Valid banks: every model kind, and a segmented set with every term kind."""
    sets = [model_set(m) for m in MODELS] + [term_set(tuple(TERMS))]
    return [encode_set(s) for s in sets]


def steepest_slope(cset: CoefficientSet) -> float:
    """G: the model's largest |d rate / d ΔV| over its span (difference quotients on a grid of
    20,001 points; the model is a smooth polynomial per segment, so 1 % covers the grid)."""
    lo, hi = (v - cset.v0 for v in cset.span_raw)
    grid = np.linspace(lo, hi, 20_001)
    rates, _ = cset.rate_model().evaluate(grid)
    return 1.01 * float(np.max(np.abs(np.diff(rates) / np.diff(grid))))


def python_verdict(content: bytes, crc: int) -> str | None:
    """Why canical's own device code refuses a bank (None: it accepts it)."""
    try:
        cset = decode_set(content, crc, "bank")
    except CanicalError as exc:
        return str(exc)
    return admission_problem(cset, AXIS, DeviceLimits(SERIAL, {AXIS: RATED}))


def load_code(
    lib: Library,
    content: bytes,
    crc: int,
    *,
    axis: str = AXIS,
    rated: float = RATED,
    inputs: tuple[str, ...] = CHANNELS,
) -> int:
    import ctypes

    device = firmware_eval.make_device(SERIAL, axis, rated, inputs)
    buf = ctypes.create_string_buffer(lib.set_size)
    return int(lib.lib.ce_load(buf, content, len(content), crc, ctypes.byref(device)))

