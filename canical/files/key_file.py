"""Key files for signing sets: ``NAME.key`` (the private key, mode 0600) and ``NAME.pub``.

Why its own format: one line, a tag naming what the file is and the key in base64, so a public
key given where a private one is expected (or a file of another tool) is refused by name, and a
key can be read and copied by people. A private key file readable by others is refused, as ssh
refuses one: whoever can read it can sign sets the vehicles trust.
"""

from __future__ import annotations

import base64
import binascii
import os
import stat
from pathlib import Path

from canical.errors import CanicalError

SECRET_TAG = "canical-ed25519-secret"
PUBLIC_TAG = "canical-ed25519-public"
KEY_BYTES = 32


def write_key_pair(name: str | os.PathLike[str], seed: bytes, public: bytes) -> tuple[Path, Path]:
    """Write ``NAME.key`` (mode 0600, never over an existing file) and ``NAME.pub``."""
    secret_path, public_path = Path(f"{name}.key"), Path(f"{name}.pub")
    for path in (secret_path, public_path):
        if path.exists():
            raise CanicalError(f"{path}: exists; not overwritten (a lost key cannot be recovered)")
    try:
        fd = os.open(secret_path, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
        with os.fdopen(fd, "w", encoding="ascii") as handle:
            os.fchmod(handle.fileno(), 0o600)
            handle.write(_line(SECRET_TAG, seed))
        public_path.write_text(_line(PUBLIC_TAG, public), encoding="ascii")
    except OSError as exc:
        raise CanicalError(f"{name}: cannot write the key pair ({exc.strerror})") from None
    return secret_path, public_path


def read_secret(path: str | os.PathLike[str]) -> bytes:
    """A private key's seed; refused if others can read the file."""
    try:
        mode = os.stat(path).st_mode
    except OSError as exc:
        raise CanicalError(f"{path}: cannot read private key ({exc.strerror})") from None
    if mode & (stat.S_IRWXG | stat.S_IRWXO):
        raise CanicalError(f"{path}: private key readable by others (mode {stat.S_IMODE(mode):04o}; "
                           "chmod 600 it)")
    return _read(path, SECRET_TAG, "private key")


def read_public(path: str | os.PathLike[str]) -> bytes:
    return _read(path, PUBLIC_TAG, "public key")


def _line(tag: str, key: bytes) -> str:
    return f"{tag} {base64.b64encode(key).decode('ascii')}\n"


def _read(path: str | os.PathLike[str], tag: str, what: str) -> bytes:
    try:
        text = Path(path).read_text(encoding="ascii")
    except FileNotFoundError:
        raise CanicalError(f"{path}: {what} not found") from None
    except (OSError, UnicodeDecodeError) as exc:
        raise CanicalError(f"{path}: cannot read {what} ({exc})") from None
    words = text.split()
    if len(words) != 2 or words[0] != tag:
        raise CanicalError(f"{path}: not a canical {what} (expected one line: {tag} BASE64)")
    try:
        key = base64.b64decode(words[1], validate=True)
    except binascii.Error:
        raise CanicalError(f"{path}: {what} is not base64") from None
    if len(key) != KEY_BYTES:
        raise CanicalError(f"{path}: {what} is {len(key)} bytes, not {KEY_BYTES}")
    return key
