"""``canical keygen NAME``: a key pair to sign coefficient sets with (``NAME.key``, ``NAME.pub``).

The private key stays at the calibration lab (mode 0600; ``canical sign --key``); the public one
goes to every vehicle that must trust the lab's sets (``trust: keys:`` in the daemon's
configuration, ``--trust`` elsewhere). An existing key is never overwritten.
"""

from __future__ import annotations

import argparse

from canical.commands import COMMANDS
from canical.files.key_file import write_key_pair


def register(sub) -> None:
    p = sub.add_parser("keygen", help=COMMANDS["keygen"])
    p.add_argument("name", metavar="NAME", help="writes NAME.key (private, mode 0600) and NAME.pub")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from canical.sets.signing import key_id_of, new_seed, public_of

    seed = new_seed()
    public = public_of(seed)
    secret_path, public_path = write_key_pair(args.name, seed, public)
    print(f"keygen: key {key_id_of(public)}: private {secret_path} (keep it at the lab), "
          f"public {public_path}")
    return 0
