"""``canical sign SET --key NAME.key``: sign a coefficient set or IMU set file in place.

The signature covers the set's canonical content (what its CRC covers), the sensor's id and a
version; a daemon that requires signatures refuses a version older than the one it runs, so
each set signed for a sensor gets a higher version (by default one more than the file has).
"""

from __future__ import annotations

import argparse

from canical.commands import COMMANDS
from canical.commands.trust_args import describe
from canical.files.key_file import read_secret

#: As :data:`canical.sets.signing.MAX_VERSION` (not imported: ``--help`` must not load yaml).
MAX_VERSION = 2**63 - 1


def register(sub) -> None:
    p = sub.add_parser("sign", help=COMMANDS["sign"])
    p.add_argument("set", metavar="SET", help="coefficient set or IMU set YAML, rewritten with its signature")
    p.add_argument("--key", required=True, metavar="NAME.key", help="the private key (canical keygen)")
    p.add_argument("--version", type=version_number, default=None, metavar="N",
                   help="the set's version [one more than the version it is signed with, else 1]")
    p.set_defaults(run=run)


def version_number(text: str) -> int:
    try:
        value = int(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"not an integer: {text!r}") from None
    if not 0 <= value <= MAX_VERSION:
        raise argparse.ArgumentTypeError(f"must be 0..{MAX_VERSION}")
    return value


def run(args: argparse.Namespace) -> int:
    from canical.sets.signed_file import sign_file

    record = sign_file(args.set, read_secret(args.key), args.version)
    print(f"sign: {args.set} {describe(record)}")
    return 0
