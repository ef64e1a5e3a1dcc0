"""``canical pull``: upload the coefficient sets an IMU runs, verified, as YAML files.

Each active bank is accepted only if its bytes match its CRC32, that CRC is the
device's "Active set id" for the axis, and every field validates. One axis
writes ``-o`` as given; several write one file per axis, ``{axis}`` in the name
replaced (or ``-x``/``-y``/``-z`` added before the suffix). ``--imu-set`` writes the IMU set
the device runs (three axes and the coupling it applies) as one file, the very set pushed.

A set the device holds signed is written with its signature (the bank's "Signature"), so the file
is the very signed set pushed. ``--trust KEY.pub`` verifies it as ``canical verify`` does a file:
a set no trusted key signed for its sensor (unsigned, another key, changed after signing, a
truncated or garbage signature) is one line, exit 2, and nothing is written.
"""

from __future__ import annotations

import argparse
from pathlib import Path

from canical.commands import COMMANDS
from canical.commands.push import add_node_arguments
from canical.commands.trust_args import add_trust_argument, describe, trusted_keys
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
    add_trust_argument(p, what=" (else nothing is written)")
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


def signed_text(args: argparse.Namespace, text: str, canonical: bytes, sensor_id: str, signature: bytes,
                where: str) -> tuple[str, str]:
    """A pulled set's text with the signature its bank carries, verified with ``--trust`` (one
    CanicalError line when not trusted), and what to say of it."""
    from canical.device.bank_signature import record_of, verify_pulled
    from canical.sets.signed_file import with_signature

    if args.trust:
        trusted = verify_pulled(signature, canonical, sensor_id, trusted_keys(args.trust), where)
        return with_signature(text, where, trusted), f", {describe(trusted)}: trusted"
    try:
        record = record_of(signature, sensor_id, where)
    except CanicalError as exc:
        return text, f", written unsigned ({exc})"
    if record is None:
        return text, ", unsigned"
    return with_signature(text, where, record), f", {describe(record)} (not verified: no --trust)"


def pull(args: argparse.Namespace, axes: tuple[str, ...]) -> int:
    from canical.device.bank_payload import encode_set
    from canical.device.sdo_download import ImuClient, active_signatures, pull_sets
    from canical.files.atomic_file import write_text_atomic
    from canical.sets import coefficient_file
    from canical.sets.coefficient_file import set_crc

    quiet_canopen_logging()
    filters = sdo_client_filters(args.node)
    with network_on(args.interface, args.channel, can_filters=filters, **bus_options(args)) as network:
        client = ImuClient(network, args.node, args.timeout)
        sets = pull_sets(client, axes)
        signatures = active_signatures(client, tuple(sets))
    if not sets:
        raise CanicalError(f"node 0x{args.node:02x}: no active coefficient set for axis {', '.join(axes)}")
    paths = output_paths(args.output, sorted(sets))
    texts = {axis: signed_text(args, coefficient_file.dumps(cset), encode_set(cset)[0], cset.sensor_id,
                               signatures.get(axis, b""), f"node 0x{args.node:02x} axis {axis}")
             for axis, cset in sets.items()}  # every set verified before any file is written
    for axis, cset in sorted(sets.items()):
        write_text_atomic(paths[axis], texts[axis][0])
        print(f"pull: axis {axis} set 0x{set_crc(cset):08x} (sensor {cset.sensor_id}) -> {paths[axis]}"
              f"{texts[axis][1]}")
    return 0


def pull_imu(args: argparse.Namespace) -> int:
    from canical.device.sdo_download import ImuClient, active_signatures, pull_imu_set
    from canical.files.atomic_file import write_text_atomic
    from canical.sets import imu_set
    from canical.sets.coefficient_file import canonical_bytes

    quiet_canopen_logging()
    filters = sdo_client_filters(args.node)
    with network_on(args.interface, args.channel, can_filters=filters, **bus_options(args)) as network:
        client = ImuClient(network, args.node, args.timeout)
        imu = pull_imu_set(client)
        signature = active_signatures(client, imu=True).get("imu", b"")
    text, said = signed_text(args, imu_set.dumps(imu), canonical_bytes(imu.to_dict()), imu.sensor_id,
                             signature, f"node 0x{args.node:02x} IMU set")
    write_text_atomic(args.output, text)
    print(f"pull: IMU set 0x{imu_set.imu_set_crc(imu):08x} (sensor {imu.sensor_id}, three axes and their "
          f"coupling) -> {args.output}{said}")
    return 0
