"""``canical push``: download coefficient sets to an IMU over CANopen SDO and activate them.

Each set goes to its axis's inactive bank, is read back and compared, then all
are activated with one write and stored (0x1010). An IMU set (``canical push imu.yaml``)
goes as its three axes and its coupling, activated together by that one write. ``--dry-run`` prints what
would be written and writes nothing. See :mod:`canical.device.sdo_download`.
"""

from __future__ import annotations

import argparse
import contextlib
from typing import TYPE_CHECKING

from canical.commands import COMMANDS
from canical.commands.trust_args import add_trust_argument, check_trusted
from canical.device.can_network import (
    DEFAULT_SDO_TIMEOUT_S,
    add_bus_arguments,
    bus_options,
    network_on,
    quiet_canopen_logging,
    sdo_client_filters,
)
from canical.errors import CanicalError

if TYPE_CHECKING:  # canopen and the set files are imported where used: not for `--help`
    from canical.sets.coefficients import CoefficientSet
    from canical.sets.imu_set import ImuSet


def add_node_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--node", type=lambda s: int(s, 0), required=True, help="IMU's CANopen node id")
    add_bus_arguments(parser)
    parser.add_argument("--timeout", type=float, default=DEFAULT_SDO_TIMEOUT_S,
                        help=f"seconds to wait for each SDO answer [{DEFAULT_SDO_TIMEOUT_S:g}]")


def register(sub) -> None:
    p = sub.add_parser("push", help=COMMANDS["push"])
    p.add_argument("coefficients", nargs="+",
                   help="coefficient set YAML, one per axis, or one IMU set (three axes and their coupling)")
    add_node_arguments(p)
    p.add_argument("--dry-run", action="store_true", help="show what would be written, write nothing")
    add_trust_argument(p, what=" (each file's; else nothing is pushed)")
    p.set_defaults(run=run)


def load_sets(paths: list[str]) -> dict[str, tuple[str, CoefficientSet]]:
    """Sets by axis; two files for one axis, or sets of different sensors, are refused."""
    from canical.sets import coefficient_file

    sets: dict[str, tuple[str, CoefficientSet]] = {}
    for path in paths:
        cset = coefficient_file.load(path)
        if cset.axis in sets:
            raise CanicalError(f"{path} and {sets[cset.axis][0]} are both for axis {cset.axis}")
        sensors = {c.sensor_id for _, c in sets.values()}
        if sensors and cset.sensor_id not in sensors:
            raise CanicalError(f"{path} is for sensor {cset.sensor_id}, the others for {sensors.pop()}")
        refuse_host_only(path, cset)
        sets[cset.axis] = (path, cset)
    return sets


def refuse_host_only(path: str, cset: CoefficientSet) -> None:
    """One line, before anything is sent, for a set holding a term the device cannot evaluate."""
    from canical.sets.term_kinds import host_only

    term = host_only(cset.terms)
    if term is not None:
        raise CanicalError(f"{path}: axis {cset.axis} {term} is evaluated on the host only (canical apply, "
                           "canical serve); the device's evaluator refuses it: not pushed")


def load_imu_set(paths: list[str]) -> tuple[str, ImuSet] | None:
    """The IMU set when the files are one (given alone), else None: they are single-axis sets."""
    from canical.sets import imu_set

    found = [p for p in paths if imu_set.is_imu_set_file(p)]
    if not found:
        return None
    if len(paths) > 1:
        raise CanicalError(f"{found[0]} is an IMU set (three axes and their coupling): give it alone")
    imu = imu_set.load(paths[0])
    for axis in imu.axes:
        refuse_host_only(paths[0], axis)
    return paths[0], imu


def offline_dry_run(sets: dict[str, tuple[str, CoefficientSet]], imu: tuple[str, ImuSet] | None,
                    why: str) -> int:
    """``--dry-run`` where the bus cannot be opened: what can be checked without the device (each
    set's bank content and the device evaluator's limits), and what could not (its serial, rated
    range, capacity and running banks), so a set can be checked at the desk before the vehicle."""
    from canical.device.bank_payload import encode_set
    from canical.sets.admission import evaluator_problem

    if imu is not None:
        sets = {c.axis: (f"{imu[0]} axes.{c.axis}", c) for c in imu[1].axes}
    print(f"push (dry run, offline): the bus is not reachable ({why})")
    for axis, (path, cset) in sorted(sets.items()):
        content, crc = encode_set(cset)
        problem = evaluator_problem(cset)
        verdict = f"the device's evaluator refuses it: {problem}" if problem else "fits its evaluator"
        print(f"  axis {axis}: set 0x{crc:08x} from {path}, {len(content)} bytes of bank content, "
              f"{len(cset.terms)} effect terms; {verdict}")
    print("push (dry run, offline): not checked without the device: its serial number against the sets' "
          "sensor id, its rated range, its bank capacity and the banks it runs; nothing written")
    return 2 if any(evaluator_problem(c) for _, c in sets.values()) else 0


def run(args: argparse.Namespace) -> int:
    from canical.device.bank_signature import bank_signatures
    from canical.device.sdo_download import ImuClient, PushPlan, push_sets

    for path in args.coefficients:  # all verified before the bus is opened
        check_trusted("push", path, args.trust)
    imu = load_imu_set(args.coefficients)
    sets = {} if imu is not None else load_sets(args.coefficients)
    quiet_canopen_logging()
    filters = sdo_client_filters(args.node)
    with contextlib.ExitStack() as stack:
        try:
            network = stack.enter_context(network_on(args.interface, args.channel, can_filters=filters,
                                                     **bus_options(args)))
        except CanicalError as exc:
            if not args.dry_run:
                raise
            return offline_dry_run(sets, imu, str(exc))
        client = ImuClient(network, args.node, args.timeout)
        client.require_canical_objects()
        result = push_sets(client, sets, imu=imu, dry_run=args.dry_run,
                           signatures=bank_signatures(args.coefficients))
    if isinstance(result, PushPlan):
        where = f"node 0x{args.node:02x} serial {result.serial} on {args.interface} {args.channel}"
        print(f"push (dry run): {where}")
        print("\n".join(result.describe()))
        print("push (dry run): nothing written")
        return 0
    print(f"push: node 0x{args.node:02x} serial {result.plan.serial} on {args.interface} {args.channel}")
    print("\n".join(result.plan.describe()))
    t = result.timings_s
    print(f"  downloaded {result.bytes_written} bytes in {t.get('download', 0):.2f} s, read back and "
          f"compared in {t.get('verify', 0):.2f} s, activated in {t.get('activate', 0):.3f} s, "
          f"stored in {t.get('store', 0):.3f} s")
    print(f"push: device runs {result.status.describe()}")
    return 0
