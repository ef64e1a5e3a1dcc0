"""``canical pull``: upload the coefficient sets an IMU runs, verified, as YAML files.

Each active bank is accepted only if its bytes match its CRC32, that CRC is the
device's "Active set id" for the axis, and every field validates. One axis
writes ``-o`` as given; several write one file per axis, ``{axis}`` in the name
replaced (or ``-x``/``-y``/``-z`` added before the suffix). ``--imu-set`` writes the IMU set
the device runs (three axes and the coupling it applies) as one file, the very set pushed.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from canical.commands import COMMANDS
from canical.commands.push import add_node_arguments
from canical.device.can_network import bus_options, network_on, quiet_canopen_logging, sdo_client_filters
from canical.errors import CanicalError
from canical.files.output_plan import output_plan
from canical.frames.imu_dictionary import AXES


def register(sub) -> None:
    p = sub.add_parser("pull", help=COMMANDS["pull"])
    add_node_arguments(p)
    p.add_argument("-o", "--output", required=True, help="YAML to write ({axis} for one file per axis)")
    p.add_argument("--axis", choices=AXES, action="append", help="only this axis (repeatable) [all active]")
    p.add_argument("--imu-set", action="store_true",
                   help="write the IMU set the device runs (three axes and their coupling) to -o")
    p.set_defaults(run=run)


def output_paths(template: str, axes: list[str]) -> dict[str, Path]:
    if "{axis}" in template:
        return {a: Path(template.replace("{axis}", a)) for a in axes}
    if len(axes) == 1:
        return {axes[0]: Path(template)}
    path = Path(template)
    return {a: path.with_name(f"{path.stem}-{a}{path.suffix}") for a in axes}


def run(args: argparse.Namespace) -> int:
    if args.imu_set:
        if args.axis:
            raise CanicalError("--imu-set reads all three axes and the coupling: no --axis with it")
        if "{axis}" in args.output:
            raise CanicalError(f"--imu-set writes one file: {args.output!r} has {{axis}} in it")
        with output_plan(args.output):
            return pull_imu(args)
    axes = tuple(args.axis) if args.axis else AXES
    # Every name the files may get: one per axis, or the name as given when one axis has a set.
    names = {*output_paths(args.output, list(axes)).values(), *output_paths(args.output, [axes[0]]).values()}
    with output_plan(*sorted(names)):
        return pull(args, axes)


def pull(args: argparse.Namespace, axes: tuple[str, ...]) -> int:
    from canical.device.sdo_download import ImuClient, pull_sets
    from canical.sets import coefficient_file
    from canical.sets.coefficient_file import set_crc

    quiet_canopen_logging()
    filters = sdo_client_filters(args.node)
    with network_on(args.interface, args.channel, can_filters=filters, **bus_options(args)) as network:
        client = ImuClient(network, args.node, args.timeout)
        sets = pull_sets(client, axes)
    if not sets:
        raise CanicalError(f"node 0x{args.node:02x}: no active coefficient set for axis {', '.join(axes)}")
    paths = output_paths(args.output, sorted(sets))
    for axis, cset in sorted(sets.items()):
        coefficient_file.save(paths[axis], cset)
        print(f"pull: axis {axis} set 0x{set_crc(cset):08x} (sensor {cset.sensor_id}) -> {paths[axis]}")
    return 0


def pull_imu(args: argparse.Namespace) -> int:
    from canical.device.sdo_download import ImuClient, pull_imu_set
    from canical.sets import imu_set

    quiet_canopen_logging()
    filters = sdo_client_filters(args.node)
    with network_on(args.interface, args.channel, can_filters=filters, **bus_options(args)) as network:
        client = ImuClient(network, args.node, args.timeout)
        imu = pull_imu_set(client)
    imu_set.save(args.output, imu)
    print(f"pull: IMU set 0x{imu_set.imu_set_crc(imu):08x} (sensor {imu.sensor_id}, three axes and their "
          f"coupling) -> {args.output}")
    return 0
