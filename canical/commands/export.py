"""``canical export dcf``: coefficient sets as a DCF any CANopen configuration tool can download.

    canical export dcf imu-x.yaml imu-y.yaml imu-z.yaml -o imu.dcf [--node 0x10] [--bank A]
                       [--channel can0 [--interface socketcan]]
    canical export dcf imu.yaml -o imu.dcf ...      (an IMU set: its three axes and its coupling)

The sets are checked as ``canical push`` checks them before writing (one per axis, one
sensor whose id is a serial number, span covering the EDS's rated range, terms the device's
evaluator holds, content within the EDS's bank capacity); the DCF is
written atomically. Offline the node cannot be asked, so the DCF describes canical's object
dictionary for whatever node id it is given, and says so; with ``--channel`` the node is asked
first, like ``push`` asks it: a node without canical's coefficient objects (a vendor's IMU) is
refused in one line, and the sets must be for its serial number and cover its rated range.
See :mod:`canical.device.dcf_export` for what the file holds and its limits.
"""

from __future__ import annotations

import argparse
from typing import TYPE_CHECKING

from canical.commands import COMMANDS
from canical.device.can_network import DEFAULT_SDO_TIMEOUT_S

if TYPE_CHECKING:
    from canical.sets.admission import DeviceLimits


def register(sub) -> None:
    p = sub.add_parser("export", help=COMMANDS["export"])
    kinds = p.add_subparsers(dest="format", metavar="FORMAT", required=True)
    d = kinds.add_parser("dcf", help="the IMU's EDS with the sets' bank values filled (CiA 306 DCF)")
    d.add_argument("coefficients", nargs="+",
                   help="coefficient set YAML, one per axis, or one IMU set (three axes and their coupling)")
    d.add_argument("-o", "--output", required=True, help="DCF file to write")
    d.add_argument("--node", type=lambda s: int(s, 0), default=0x10, help="node id to commission [0x10]")
    d.add_argument(
        "--bank",
        choices=("A", "B"),
        default="A",
        help="bank to fill: one the device is not running (a fresh device runs none) [A]",
    )
    d.add_argument("--bitrate", type=int, default=500, help="bus bit rate in kbit/s [500]")
    d.add_argument("--rated-range", type=_rated_range, default=None, metavar="DPS",
                   help="the device's rated range, deg/s, that each set's span must cover, as configured "
                   "on the device (object 'Rated range'); 0: no check [the device's with --channel, "
                   "else the EDS's default]")
    d.add_argument("--channel", help="ask the node on this CAN channel before writing: that it carries "
                   "canical's objects, its serial number and rated range [offline: not asked]")
    d.add_argument("--interface", default="socketcan", help="python-can interface for --channel [socketcan]")
    d.add_argument("--timeout", type=float, default=DEFAULT_SDO_TIMEOUT_S,
                   help=f"with --channel: seconds to wait for each SDO answer [{DEFAULT_SDO_TIMEOUT_S:g}]")
    d.set_defaults(run=run)


def _rated_range(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError("--rated-range takes a number of deg/s") from None
    if not 0 <= value < float("inf"):
        raise argparse.ArgumentTypeError("--rated-range must be a finite number of deg/s, 0 or more")
    return value


def run(args: argparse.Namespace) -> int:
    from canical.files.output_plan import output_plan

    with output_plan(args.output):
        return export_dcf(args)


def export_dcf(args: argparse.Namespace) -> int:
    from pathlib import Path

    from canopen.objectdictionary import ODVariable

    from canical.commands.push import load_imu_set, load_sets
    from canical.device.bank_payload import encode_coupling
    from canical.device.bank_signature import bank_signatures
    from canical.device.dcf_export import bank_values, dcf_text
    from canical.errors import CanicalError
    from canical.files.atomic_file import write_text_atomic
    from canical.frames.imu_dictionary import (
        default_value,
        eds_path,
        imu_objects,
        member,
        object_dictionary,
        sensor_id_for_serial,
    )
    from canical.sets.admission import DeviceLimits, admission_problem
    from canical.sets.coefficient_file import set_crc

    if not 1 <= args.node <= 127:
        raise CanicalError(f"--node {args.node}: a CANopen node id is 1..127")
    imu = load_imu_set(args.coefficients)
    if imu is None:
        sets = load_sets(args.coefficients)
    else:
        sets = {c.axis: (f"{imu[0]} axes.{c.axis}", c) for c in imu[1].axes}
    sensor = next(iter(sets.values()))[1].sensor_id
    if imu is not None and imu[1].sensor_id != sensor:
        raise CanicalError(f"{imu[0]}: sensor.id {imu[1].sensor_id!r} is not its axes' {sensor!r}")
    if not sensor.isdigit() or sensor_id_for_serial(int(sensor)) != sensor:
        raise CanicalError(
            f"sensor.id {sensor!r} is not an IMU serial number (decimal text, as in 0x1018 sub 4): a "
            "device with canical's firmware admits only a set made for its own serial (calibrate "
            "with --sensor SERIAL); an IMU without that firmware is corrected by canical serve from "
            "the set file, no DCF needed"
        )
    objects = imu_objects()
    od = object_dictionary(args.node)
    device = None if args.channel is None else node_limits(args)
    rated = {}
    for axis, (index, sub) in objects.rated_range.items():
        declared = args.rated_range
        if declared is None:
            declared = (float(default_value(member(od, index, sub))) if device is None
                        else device.rated_range_dps[axis])
        rated[axis] = declared
    capacity = device.bank_capacity if device is not None else None
    if device is None:
        entry = od[objects.capacity[0]]  # a variable (0x2200): the EDS's bank capacity
        capacity = int(default_value(entry)) if isinstance(entry, ODVariable) else None
    limits = DeviceLimits(int(sensor) if device is None else device.serial, rated, capacity)
    for axis, (path, cset) in sets.items():
        problem = admission_problem(cset, axis, limits)
        if problem:
            source = ("--rated-range" if args.rated_range is not None
                      else "the EDS's default; --rated-range sets the device's" if device is None
                      else f"node 0x{args.node:02x}")
            raise CanicalError(f"{path}: {problem} ({source})")
    coupling = None if imu is None else encode_coupling(imu[1])
    signatures = bank_signatures(args.coefficients)
    values = bank_values(objects, {a: c for a, (_, c) in sets.items()}, args.bank, coupling, signatures)
    out = Path(args.output)
    text = dcf_text(eds_path().read_text(encoding="utf-8"), values, node_id=args.node,
                    bitrate_kbit=args.bitrate, name=out.name)  # fmt: skip
    write_text_atomic(out, text)
    axes = ", ".join(f"{a} set 0x{set_crc(c):08x}" for a, (_, c) in sorted(sets.items()))
    if coupling is not None:
        axes += f", coupling of IMU set 0x{coupling.imu_set_id:08x}"
    signed = f"; signed: {', '.join(sorted(signatures))}" if signatures else "; unsigned"
    print(f"export: {out} for node 0x{args.node:02x}, serial {sensor}, bank {args.bank}: {axes}{signed}")
    if device is None:
        print(f"export: offline: node 0x{args.node:02x} was not asked whether it carries canical's "
              "coefficient objects (--channel asks it)")
    return 0


def node_limits(args: argparse.Namespace) -> DeviceLimits:
    """The node on ``--channel`` asked as ``push`` asks it: canical's objects, serial, rated range."""
    from canical.device.can_network import network_on, quiet_canopen_logging, sdo_client_filters
    from canical.device.sdo_download import ImuClient

    quiet_canopen_logging()
    with network_on(args.interface, args.channel, can_filters=sdo_client_filters(args.node)) as network:
        client = ImuClient(network, args.node, args.timeout)
        client.require_canical_objects()
        return client.limits()
