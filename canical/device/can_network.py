"""Opening a CANopen network on a python-can interface, with a one-line error when it fails.

Every bus-facing command (emulate, push, pull, the demo) opens its bus here, so
``--interface``/``--channel`` mean the same everywhere and a missing interface
(no vcan0, no driver) reads as one line, not a traceback.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Iterator
from typing import TYPE_CHECKING, Any

from canical.errors import CanicalError

if TYPE_CHECKING:
    import canopen

# Seconds to wait for each SDO answer; here, not in sdo_download, so that the commands' --help
# can show it without importing canopen.
DEFAULT_SDO_TIMEOUT_S = 1.0


def quiet_canopen_logging() -> None:
    """Keep canopen's own log lines (per-transfer warnings) off a command's stderr.

    A command reports a failed transfer itself, as one line; canopen's warning about the
    same abort would otherwise reach stderr through logging's last-resort handler.
    """
    logging.getLogger("canopen").addHandler(logging.NullHandler())
    logging.getLogger("can").addHandler(logging.NullHandler())


def open_network(interface: str, channel: str, *, listeners: list[Any] | None = None,
                 **options: Any) -> canopen.Network:
    """A connected canopen network; :class:`CanicalError` if the interface cannot be opened.

    ``listeners`` (python-can listeners) receive from the first frame (and error) on.
    """
    import canopen  # here, not at the top: every command's --help imports this module

    network = canopen.Network()
    network.listeners.extend(listeners or [])
    try:
        network.connect(interface=interface, channel=channel, **options)
    except Exception as exc:  # python-can raises OSError, CanError, ValueError, ImportError...
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CanicalError(f"cannot open CAN interface {interface} channel {channel}: {first}") from None
    return network


def disconnect_quietly(network: canopen.Network) -> None:
    """Disconnect, whatever state the bus is in.

    canopen re-raises a failed receive thread's exception from ``disconnect``; after an outage
    that is old news, not a reason for a traceback at shutdown.
    """
    with contextlib.suppress(Exception):  # python-can and canopen raise many types here
        network.disconnect()
    network.bus = None


def reconnect_network(network: canopen.Network, interface: str, channel: str, **options: Any) -> None:
    """Close ``network``'s bus and open it again (its nodes stay): after the interface went away.

    :class:`CanicalError` (one line) when it cannot be opened yet.
    """
    disconnect_quietly(network)
    try:
        network.connect(interface=interface, channel=channel, **options)
    except Exception as exc:  # as in open_network
        network.bus = None
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CanicalError(f"cannot reopen CAN interface {interface} channel {channel}: {first}") from None


@contextlib.contextmanager
def network_on(interface: str, channel: str, **options: Any) -> Iterator[canopen.Network]:
    """:func:`open_network` as a context manager that always disconnects."""
    network = open_network(interface, channel, **options)
    try:
        yield network
    finally:
        network.disconnect()


def sdo_client_filters(node_id: int) -> list[dict[str, Any]]:
    """Receive filters for an SDO client of one node: only its responses (0x580 + node id).

    On SocketCAN the kernel drops the rest, so a tool on a busy bus (or in a slow VM) does
    not spend its time decoding raw frames it never looks at.
    """
    return [{"can_id": 0x580 + node_id, "can_mask": 0x7FF, "extended": False}]


def sdo_server_filters(node_id: int) -> list[dict[str, Any]]:
    """Receive filters for a device: its SDO requests (0x600 + node id) and NMT commands (0x000)."""
    return [
        {"can_id": 0x600 + node_id, "can_mask": 0x7FF, "extended": False},
        {"can_id": 0x000, "can_mask": 0x7FF, "extended": False},
    ]


def add_bus_arguments(parser: Any, *, channel_required: bool = True) -> None:
    """``--channel``, ``--interface`` and ``--bitrate``, the same for every bus command."""
    parser.add_argument("--channel", required=channel_required, help="CAN channel (vcan0, can0...)")
    parser.add_argument(
        "--interface", default="socketcan", help="python-can interface [socketcan]; 'virtual' in-process"
    )
    parser.add_argument("--bitrate", type=int, help="bit rate, for interfaces that set it")


def bus_options(args: Any) -> dict[str, Any]:
    return {"bitrate": args.bitrate} if getattr(args, "bitrate", None) else {}
