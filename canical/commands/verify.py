"""``canical verify SET --trust NAME.pub``: whether a set file is signed by a trusted key.

One line either way; exit 0 when a trusted key signed the set's content for its sensor, 2 when
not (unsigned, another key, changed after signing, a damaged signature, a damaged set).
"""

from __future__ import annotations

import argparse

from canical.commands import COMMANDS
from canical.commands.trust_args import add_trust_argument, describe, trusted_keys, verify_set_file


def register(sub) -> None:
    p = sub.add_parser("verify", help=COMMANDS["verify"])
    p.add_argument("set", metavar="SET", help="coefficient set or IMU set YAML")
    add_trust_argument(p, required=True)
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from canical.sets.signed_file import read_set_file

    keys = trusted_keys(args.trust)
    checked = read_set_file(args.set)
    record = verify_set_file(args.set, keys, checked)
    print(f"verify: {args.set}: set 0x{checked.crc:08x} {describe(record)}: trusted")
    return 0
