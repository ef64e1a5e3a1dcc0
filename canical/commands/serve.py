"""``canical serve``: run the real-time correction daemon on one CAN interface.

The configuration is checked completely before anything opens (a bad one is refused with one
line naming the key, exit status 2). ``--check`` also loads every coefficient set and stops
there, so an operator or an ``ExecStartPre=`` can vet a change before it reaches the vehicle.
Logs go to stdout, one line each, without timestamps when journald records them anyway.
"""

from __future__ import annotations

import argparse
import logging
import os
import sys
from typing import TYPE_CHECKING

from canical.commands import COMMANDS
from canical.errors import CanicalError

if TYPE_CHECKING:
    from canical.bus.active_sets import Origin
    from canical.bus.daemon_config import DaemonConfig

# The daemon's modules (python-can, cantools, numpy) are imported by `run`, so that `--help`
# answers at once.


def register(sub) -> None:
    p = sub.add_parser("serve", help=COMMANDS["serve"])
    p.add_argument("--config", required=True, help="daemon configuration YAML")
    p.add_argument("--channel", help="CAN interface, overriding bus.channel (e.g. the unit's %%i)")
    p.add_argument("--check", action="store_true",
                   help="check the configuration and load every coefficient set, then exit")
    p.add_argument("-v", "--verbose", action="store_true", help="debug logging")
    p.set_defaults(run=run)


def setup_logging(verbose: bool) -> None:
    """One line per record on stdout; journald adds its own timestamps and priority."""
    fmt = "%(levelname)s %(message)s" if os.environ.get("JOURNAL_STREAM") else (
        "%(asctime)s %(levelname)s %(message)s")
    handler = logging.StreamHandler(sys.stdout)
    handler.setFormatter(logging.Formatter(fmt))
    root = logging.getLogger()
    root.handlers[:] = [handler]
    root.setLevel(logging.DEBUG if verbose else logging.INFO)
    if not verbose:
        logging.getLogger("can").setLevel(logging.WARNING)
        logging.getLogger("canopen").setLevel(logging.WARNING)  # SDO chatter when reading the device


def check_device(config) -> None:
    """``device:``: the node must carry canical's coefficient objects (a vendor's IMU does not:
    one line, exit 2). A node that does not answer is only noted: the files are the fallback."""
    from canical.device.can_network import open_network, quiet_canopen_logging, sdo_client_filters
    from canical.device.sdo_download import DeviceSilent, ImuClient
    from canical.errors import CanicalError

    device = config.device
    quiet_canopen_logging()
    try:
        network = open_network(config.interface, config.channel, can_filters=sdo_client_filters(device.node),
                               **config.bus_options)
    except CanicalError as exc:
        print(f"device: not checked ({exc}); the coefficient files will be used if it does not answer")
        return
    try:
        client = ImuClient(network, device.node, device.timeout_s)
        try:
            client.require_canical_objects()
        except DeviceSilent as exc:
            print(f"device: {exc}; the coefficient files will be used")
            return
        print(f"device: node 0x{device.node:02x} carries canical's coefficient objects")
    finally:
        network.disconnect()


#: What to do on a kernel without SocketCAN: its modules, or another python-can interface.
NO_SOCKETCAN_HINT = ("load its modules (modprobe can-raw; and vcan for a virtual bus), or name a python-can "
                     "interface that works here in bus.interface")


def socketcan_missing() -> str | None:
    """Why this kernel cannot open a SocketCAN socket at all (None: it can).

    Why ask before starting: an interface that is down comes back, and the daemon waits for it;
    a kernel without ``AF_CAN`` never will, and the daemon retried it forever (125 reopen
    attempts in 240 s). EAFNOSUPPORT is that kernel's answer; any other error is the interface's.
    """
    import errno
    import socket

    family = getattr(socket, "AF_CAN", None)
    if family is None:
        return "this Python has no AF_CAN"
    try:
        socket.socket(family, socket.SOCK_RAW, socket.CAN_RAW).close()
    except OSError as exc:
        if exc.errno == errno.EAFNOSUPPORT:
            return f"this kernel has no SocketCAN (socket(AF_CAN): {exc.strerror})"
    return None


def served_axes(config: DaemonConfig) -> str:
    """Which axes the daemon corrects and which it does not: a single-axis sensor's configuration
    leaves two out, and whoever checks it should see that they are not served."""
    corrected = [a.axis for a in config.axes if a.present and (a.coefficients or config.imu_set)]
    other = [a.axis for a in config.axes if a.axis not in corrected]
    served = f"corrected: axis {', '.join(corrected)}" if corrected else "corrected: no axis"
    return served + (f"; not corrected: {', '.join(other)}" if other else "")


def signed_note(origin: Origin) -> str:
    """What ``--check`` adds to a set's line under ``trust:``: its signed version, or the problem
    let through (``require: false``)."""
    if origin.warning is not None:
        return f"; warning: {origin.warning}"
    return "" if origin.version is None else f", signed by a trusted key as version {origin.version}"


def run(args: argparse.Namespace) -> int:
    from canical.bus import active_sets
    from canical.bus.daemon import Daemon
    from canical.bus.daemon_config import load_config
    from canical.sets.imu_set import imu_set_crc

    config = load_config(args.config, channel=args.channel)
    missing = socketcan_missing() if config.interface == "socketcan" else None
    if missing is not None and not args.check:
        raise CanicalError(f"{config.path}: bus.interface socketcan: {missing}: {NO_SOCKETCAN_HINT}")
    if args.check:
        if config.imu_set is not None:
            imu, correctors, origin = active_sets.load_imu_origin(config, config.imu_set, None)
            print(f"imu set 0x{imu_set_crc(imu):08x} from {config.imu_set}: axes "
                  + ", ".join(f"{c.cset.axis} 0x{c.set_id:08x}" for c in correctors) + ", coupling checked"
                  + signed_note(origin))
        for axis in config.axes if config.imu_set is None else ():
            if not axis.present:
                print(f"axis {axis.axis}: not in axes (absent: not read, not corrected)")
                continue
            if axis.coefficients is None:
                print(f"axis {axis.axis}: no coefficients configured (sent uncalibrated)")
                continue
            corrector, origin = active_sets.load_axis_origin(config, axis.axis, axis.coefficients, None)
            print(f"axis {axis.axis}: set 0x{corrector.set_id:08x} from {axis.coefficients}"
                  + signed_note(origin))
        if config.device is not None:
            check_device(config)
        print(served_axes(config))
        if config.trust is None:
            print("note: sets are not authenticated (no trust: in the configuration)")
        if config.field_log is not None:
            log = config.field_log
            print(f"field log: {log.directory} for vehicle {log.vehicle_id}, "
                  f"at most {log.max_bytes / 1e6:g} MB")
        print(f"{config.path}: configuration OK ({config.interface} {config.channel})")
        if missing is not None:  # the configuration may be for the vehicle, not this machine
            print(f"note: serve would not start on this machine: {missing}: {NO_SOCKETCAN_HINT}")
        return 0
    setup_logging(args.verbose)
    daemon = Daemon(config)
    daemon.install_signal_handlers()
    try:
        return daemon.run()
    finally:
        daemon.notifier.close()
