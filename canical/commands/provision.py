"""``canical provision --key lab.pub --node N``: give an IMU the key it checks signed sets against.

The IMU (canical's firmware, or ``canical emulate``) stores the lab's public key (0x2232) while
it is in its provisioning state; from then on it activates only sets that key signed for it.
``--close`` then closes provisioning for good (0x2233), so no node on the bus can put another
key in: do it at the lab or the end of line, before the IMU goes into a vehicle. A closed device
holding the same key is reported, not an error; one holding another key is one line, exit 2.
"""

from __future__ import annotations

import argparse

from canical.commands import COMMANDS
from canical.commands.push import add_node_arguments
from canical.device.can_network import bus_options, network_on, quiet_canopen_logging, sdo_client_filters


def register(sub) -> None:
    p = sub.add_parser("provision", help=COMMANDS["provision"])
    p.add_argument("--key", required=True, metavar="KEY.pub", help="the lab's public key (canical keygen)")
    add_node_arguments(p)
    p.add_argument("--close", action="store_true",
                   help="close provisioning for good once the key is written and read back")
    p.set_defaults(run=run)


def run(args: argparse.Namespace) -> int:
    from canical.device.provisioning import provision
    from canical.device.sdo_download import ImuClient
    from canical.files.key_file import read_public

    key = read_public(args.key)
    quiet_canopen_logging()
    filters = sdo_client_filters(args.node)
    with network_on(args.interface, args.channel, can_filters=filters, **bus_options(args)) as network:
        client = ImuClient(network, args.node, args.timeout)
        client.require_canical_objects()
        trust = provision(client, key, close=args.close)
    closed = "open (--close closes it)" if trust.open else "closed for good"
    print(f"provision: node 0x{args.node:02x} trusts key {trust.key_id}; provisioning {closed}; "
          f"rollback counter {trust.counter}")
    return 0
