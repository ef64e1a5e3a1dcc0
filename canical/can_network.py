"""Opening a CANopen network on a python-can interface, with a one-line error when it fails.

Every bus-facing command (emulate, push, pull, the demo) opens its bus here, so
``--interface``/``--channel`` mean the same everywhere and a missing interface
(no vcan0, no driver) reads as one line, not a traceback.
"""

from __future__ import annotations

import contextlib
from collections.abc import Iterator
from typing import Any

import canopen

from canical.errors import CanicalError


def open_network(interface: str, channel: str, **options: Any) -> canopen.Network:
    """A connected canopen network; :class:`CanicalError` if the interface cannot be opened."""
    network = canopen.Network()
    try:
        network.connect(interface=interface, channel=channel, **options)
    except Exception as exc:  # python-can raises OSError, CanError, ValueError, ImportError...
        first = str(exc).splitlines()[0] if str(exc) else type(exc).__name__
        raise CanicalError(f"cannot open CAN interface {interface} channel {channel}: {first}") from None
    return network


@contextlib.contextmanager
def network_on(interface: str, channel: str, **options: Any) -> Iterator[canopen.Network]:
    """:func:`open_network` as a context manager that always disconnects."""
    network = open_network(interface, channel, **options)
    try:
        yield network
    finally:
        network.disconnect()


def add_bus_arguments(parser: Any, *, channel_required: bool = True) -> None:
    """``--channel``, ``--interface`` and ``--bitrate``, the same for every bus command."""
    parser.add_argument("--channel", required=channel_required, help="CAN channel (vcan0, can0...)")
    parser.add_argument(
        "--interface", default="socketcan", help="python-can interface [socketcan]; 'virtual' in-process"
    )
    parser.add_argument("--bitrate", type=int, help="bit rate, for interfaces that set it")


def bus_options(args: Any) -> dict[str, Any]:
    return {"bitrate": args.bitrate} if getattr(args, "bitrate", None) else {}
