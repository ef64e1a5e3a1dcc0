"""Signed sets for the tests: a lab's key pair, a signed copy of a set, and every way a set can fail
to be one the lab signed (unsigned, another key, tampered, another sensor, rolled back, a truncated
or garbage signature), each as a file the loaders and verifiers are given.

Why files built from real sets: the refusals must happen where a vehicle meets them, in the
file readers and the daemon's reload, not in a mock of them.
"""

from __future__ import annotations

import shutil
import struct
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import yaml

from canical.files.key_file import read_secret, write_key_pair
from canical.sets.coefficient_file import content_crc
from canical.sets.signed_file import sign_file
from canical.sets.signing import new_seed, public_of


@dataclass(frozen=True)
class Lab:
    """The trusted lab's key pair and a stranger's."""

    key: Path
    pub: Path
    other_key: Path
    other_pub: Path


def make_lab(folder: Path) -> Lab:
    folder.mkdir(parents=True, exist_ok=True)
    keys = []
    for name in ("lab", "stranger"):
        seed = new_seed()
        keys += write_key_pair(folder / name, seed, public_of(seed))
    return Lab(*keys)


def signed_copy(src: Path, dst: Path, key: Path, version: int = 1) -> Path:
    shutil.copyfile(src, dst)
    sign_file(dst, read_secret(key), version)
    return dst


def edit(path: Path, change: Callable[[dict[str, Any]], None], *, recompute_crc: bool) -> Path:
    """Change a set file's content in place (its CRC recomputed, or left as it was)."""
    content = yaml.safe_load(path.read_text())
    change(content)
    if recompute_crc:
        content["crc32"] = f"0x{content_crc(content):08x}"
    path.write_text(yaml.safe_dump(content, sort_keys=False, default_flow_style=None, width=100))
    return path


def flip_bit(value: float) -> float:
    """The float with the lowest bit of its mantissa flipped: the smallest tampering there is."""
    (bits,) = struct.unpack(">Q", struct.pack(">d", value))
    (out,) = struct.unpack(">d", struct.pack(">Q", bits ^ 1))
    return float(out)


def _model(content: dict[str, Any]) -> dict[str, Any]:
    """The first axis's model (of a single-axis set, or of an IMU set's x axis)."""
    axis = content["axes"]["x"] if content.get("kind") == "imu-set" else content
    model: dict[str, Any] = axis["model"]
    return model


def _tamper(content: dict[str, Any]) -> None:
    coefficients = _model(content)["coefficients"]
    coefficients[0][1] = flip_bit(coefficients[0][1])


def _sensor(content: dict[str, Any]) -> None:
    content["signature"]["sensor"] = "ANOTHER-SENSOR"


def _truncate(content: dict[str, Any]) -> None:
    content["signature"]["ed25519"] = content["signature"]["ed25519"][:44]


def _garbage(content: dict[str, Any]) -> None:
    content["signature"] = "garbage, not a signature"


#: Each refused case: what it is, and the words its one-line refusal says.
REFUSALS = {
    "unsigned": "not signed",
    "untrusted": "not trusted",
    "tampered": "CRC mismatch",
    "tampered-crc-recomputed": "does not match the content",
    "another-sensor": "signed for sensor ANOTHER-SENSOR",
    "rollback": "rollback",
    "truncated": "truncated",
    "garbage": "signature: must be a mapping",
}


def refused_case(case: str, src: Path, folder: Path, lab: Lab, *, version: int = 1) -> Path:
    """A copy of ``src`` refused for reason ``case`` (``rollback``: signed as ``version - 1``, to be
    offered while ``version`` runs)."""
    dst = folder / f"{case}-{src.name}"
    if case == "unsigned":
        shutil.copyfile(src, dst)
        return dst
    if case == "untrusted":
        return signed_copy(src, dst, lab.other_key, version)
    if case == "rollback":
        return signed_copy(src, dst, lab.key, version - 1)
    signed_copy(src, dst, lab.key, version)
    change = {"tampered": _tamper, "tampered-crc-recomputed": _tamper, "another-sensor": _sensor,
              "truncated": _truncate, "garbage": _garbage}[case]
    return edit(dst, change, recompute_crc=case != "tampered")
