"""``--trust KEY.pub``: the public keys a command verifies sets against, for every command that takes them.

Why one place: ``verify``, ``apply``, ``serve --check`` and ``push`` must read keys and refuse a
set the same way the daemon does, so a set that passes on the bench passes on the vehicle.
"""

from __future__ import annotations

import argparse
from collections.abc import Sequence
from typing import TYPE_CHECKING

from canical.files.key_file import read_public

if TYPE_CHECKING:  # yaml, numpy and PyNaCl only when a command runs (--help answers at once)
    from canical.sets.signed_file import SetFile
    from canical.sets.signing import SignatureRecord, TrustedKey


def add_trust_argument(p: argparse.ArgumentParser, *, required: bool = False, what: str = "") -> None:
    p.add_argument("--trust", action="append", metavar="KEY.pub", required=required, default=None,
                   help=f"a public key (canical keygen) whose signature a set must carry{what} (repeatable)")


def trusted_keys(paths: Sequence[str] | None) -> tuple[TrustedKey, ...]:
    """The keys given with ``--trust`` (none: an empty tuple, nothing verified)."""
    from canical.sets.signing import TrustedKey

    return tuple(TrustedKey(read_public(p), str(p)) for p in paths or ())


def describe(record: SignatureRecord) -> str:
    return f"signed by key {record.key_id}, version {record.version}, for sensor {record.sensor_id}"


def verify_set_file(path: str, keys: tuple[TrustedKey, ...], checked: SetFile) -> SignatureRecord:
    """The record of a set file signed by one of ``keys``; else one CanicalError line."""
    from canical.sets.signed_file import verified

    return verified(checked.signed, keys, None, str(path))


def check_trusted(command: str, path: str, trust: Sequence[str] | None) -> None:
    """With ``--trust``: refuse (one line) a set file no trusted key signed, else say who signed it.

    Read, checked and verified before the command does anything with the file."""
    if not trust:
        return
    from canical.sets.signed_file import read_set_file

    keys = trusted_keys(trust)
    record = verify_set_file(path, keys, read_set_file(path))
    print(f"{command}: {path} {describe(record)}: trusted")
