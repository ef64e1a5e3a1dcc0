"""Fixtures of the firmware evaluator's tests: the library built from firmware/, and the fuzz
driver built with it under AddressSanitizer and UBSan (once per module)."""

from __future__ import annotations

import subprocess
from pathlib import Path

import pytest
from support.firmware_build import (
    FIRMWARE,
    SANITIZE,
)

from canical.device.firmware_eval import CFLAGS, Library, compile_library


@pytest.fixture(scope="module")
def lib(tmp_path_factory) -> Library:
    """Built from firmware/ with -std=c99 -Wall -Wextra -Werror -O2 (a warning fails the test)."""
    out = tmp_path_factory.mktemp("fw") / "libcanical_eval.so"
    compile_library(out, sources=FIRMWARE)
    return Library(out)


@pytest.fixture(scope="module")
def sanitized_driver(tmp_path_factory) -> Path:
    """firmware/fuzz_driver.c with the library, under AddressSanitizer and UBSan."""
    exe = tmp_path_factory.mktemp("fuzz") / "fuzz_driver"
    cmd = [
        "cc",
        *CFLAGS[:5],
        *SANITIZE,
        "-o",
        str(exe),
        str(FIRMWARE / "fuzz_driver.c"),
        str(FIRMWARE / "canical_eval.c"),
    ]
    done = subprocess.run(cmd, capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    return exe


@pytest.fixture(scope="module")
def lib_for_hypothesis(lib):
    return lib
