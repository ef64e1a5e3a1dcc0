"""``canical install-service``: install canical as a systemd service on this machine.

See :mod:`canical.bus.service_install` for why it goes under ``/opt/canical`` and ``/etc/canical``.
Idempotent (a second run says "nothing to do"); ``--dry-run`` prints what it would do.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from canical import __version__
from canical.bus.service_install import Layout, Request, install
from canical.commands import COMMANDS


def register(sub) -> None:
    p = sub.add_parser("install-service", help=COMMANDS["install-service"])
    p.add_argument("--wheel", help=f"canical wheel to install [canical=={__version__} from the index]")
    p.add_argument("--find-links", action="append", default=[], metavar="DIR",
                   help="directory of wheels for the dependencies (repeatable; an offline vehicle)")
    p.add_argument("--no-index", action="store_true", help="do not use the package index")
    p.add_argument("--channel", default="can0", help="CAN interface: /etc/canical/CHANNEL.yaml [can0]")
    p.add_argument("--set", dest="sets", action="append", default=[], metavar="YAML",
                   help="coefficient set to install as /etc/canical/imu-AXIS.yaml (repeatable)")
    p.add_argument("--bitrate", type=int,
                   help="bit rate of a real controller (/etc/canical/CHANNEL.env); none for vcan")
    p.add_argument("--prefix", type=Path, default=Layout.prefix, help="venv parent [/opt/canical]")
    p.add_argument("--etc", type=Path, default=Layout.etc, help="configuration folder [/etc/canical]")
    p.add_argument("--bin-link", type=Path, default=Layout.bin_link,
                   help="the canical the units run [/usr/local/bin/canical]")
    p.add_argument("--unit-dir", type=Path, default=Layout.unit_dir, help="[/etc/systemd/system]")
    p.add_argument("--python", type=Path, default=Layout.python,
                   help="system interpreter for the venv [/usr/bin/python3]")
    p.add_argument("--dry-run", action="store_true", help="print the changes, make none")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    layout = Layout(prefix=args.prefix, etc=args.etc, bin_link=args.bin_link, unit_dir=args.unit_dir,
                    python=args.python)
    request = Request(package=args.wheel or f"canical=={__version__}", channel=args.channel,
                      sets=tuple(Path(s) for s in args.sets), bitrate=args.bitrate,
                      find_links=tuple(Path(d) for d in args.find_links), no_index=args.no_index)
    install(layout, request, dry_run=args.dry_run)
    return 0
