"""The compiled per-frame path against the reference path, frame for frame, in-process.

The same IMU stream, with every kind of frame the daemon must drop mixed in and a reload of
the sets half-way, goes through a reference daemon (``compiled=False``: python-can messages,
cantools, ``Corrector.correct_one``) and through a compiled one reading the kernel's frame
layout from a stand-in raw socket (its receive loop, parse, generated codecs and correctors,
``send`` on the socket). Both must send the same payloads and count the same things.
"""

from __future__ import annotations

import errno
import socket
import struct
from pathlib import Path

import can
import pytest
from can.interfaces.socketcan.constants import CAN_EFF_FLAG, CAN_ERR_FLAG, CAN_RTR_FLAG
from support.daemon_fixtures import ALL_TERMS, imu_stream, write_config, write_sets

from canical.bus.daemon import Daemon
from canical.bus.daemon_config import load_config
from canical.bus.link import BusLink, SocketLink
from canical.bus.socketcan_constants import FRAME_HEAD, TIMEVAL
from canical.files import atomic_file


class StandInSocket:
    """What the daemon uses of python-can's raw socket: recvmsg with a timestamp, send."""

    family = socket.AF_CAN

    def __init__(self, daemon: Daemon, frames: list[tuple[bytes, float]]) -> None:
        self.daemon = daemon
        self.frames = iter(frames)
        self.sent: list[bytes] = []
        self.full = False

    def gettimeout(self) -> None:
        return None

    def setsockopt(self, level: int, option: int, value: bytes) -> None:
        assert option == socket.SO_RCVTIMEO and TIMEVAL.unpack(value) != (0, 0)  # 0 would block for ever

    def recvmsg(self, size: int, ancsize: int):
        got = next(self.frames, None)
        if got is None:
            self.daemon._running = False
            raise BlockingIOError
        cf, stamp = got
        return cf, [(socket.SOL_SOCKET, 35, TIMEVAL.pack(int(stamp), round(stamp % 1 * 1e9)))], 0, None

    def close(self) -> None:
        pass

    def send(self, frame: bytes, flags: int = 0) -> int:
        if self.full:
            raise OSError(errno.ENOBUFS, "No buffer space available")
        _, length, _, _ = FRAME_HEAD.unpack_from(frame)
        self.sent.append(frame[8:8 + length])
        return len(frame)


class ReplayBus:
    """A python-can bus stand-in: ``recv`` hands out ``msgs`` (then stops the daemon), ``send``
    goes to ``bus`` (when given)."""

    def __init__(self, daemon: Daemon, msgs: list[can.Message], bus: object = None) -> None:
        self.daemon, self.msgs, self.bus = daemon, iter(msgs), bus

    def recv(self, timeout: float | None = None) -> can.Message | None:
        msg = next(self.msgs, None)
        if msg is None:
            self.daemon._running = False
        return msg

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.bus is not None:
            self.bus.send(msg)  # type: ignore[attr-defined]

    def shutdown(self) -> None:
        pass


def feed(daemon: Daemon, msgs: list[can.Message], bus: object = None) -> None:
    """python-can messages through the daemon's receive loop on a python-can link (as on an
    interface that is not SocketCAN); what it sends goes to ``bus``."""
    if bus is None and isinstance(daemon.sender.link, BusLink):  # the bus the test set up
        bus = daemon.sender.link.bus
    daemon.sender.link = BusLink(ReplayBus(daemon, msgs, bus))  # type: ignore[arg-type]
    daemon._running = True
    daemon.serve(until=float("inf"))


def serve_socket(daemon: Daemon, sock: StandInSocket, out: StandInSocket | None = None) -> None:
    """The stand-in socket's frames through the daemon's receive loop (it stops the daemon at the end)."""
    daemon.sender.link = SocketLink(sock)  # type: ignore[arg-type]
    if out is not None:
        daemon.sender.out = SocketLink(out)  # type: ignore[arg-type]
    daemon._running = True
    daemon.serve(until=float("inf"))


def handler_source(daemon: Daemon) -> str:
    """The source of the raw frame's handler for the daemon's sets and links ("": the reference)."""
    return getattr(daemon.raw_path.handler(daemon.sets), "source", "")


def kernel_frame(msg: can.Message) -> bytes:
    """``msg`` as SocketCAN hands it to a raw socket (classic or FD layout)."""
    can_id = msg.arbitration_id | (CAN_EFF_FLAG if msg.is_extended_id else 0)
    can_id |= (CAN_RTR_FLAG if msg.is_remote_frame else 0) | (CAN_ERR_FLAG if msg.is_error_frame else 0)
    data = bytes(msg.data)
    size = 64 if msg.is_fd else 8
    return FRAME_HEAD.pack(can_id, len(data), 0, 0) + data.ljust(size, b"\0")


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    write_sets(tmp_path, terms=ALL_TERMS)
    (tmp_path / "next").mkdir()
    write_sets(tmp_path / "next", terms=ALL_TERMS, variant=1)
    return tmp_path


def stream_with_faults(n: int) -> list[can.Message]:
    stream = imu_stream(n)
    msgs = [can.Message(arbitration_id=fid, data=data, is_extended_id=False, timestamp=100.0 + i * 0.001)
            for i, (fid, data) in enumerate(stream.frames)]
    raw = stream.frames[stream.raw_index[0]][1]
    faults = [can.Message(arbitration_id=0x190, data=raw[:5], is_extended_id=False),
              can.Message(arbitration_id=0x555, data=raw, is_extended_id=False),
              can.Message(arbitration_id=0x190, data=raw, is_extended_id=True),
              can.Message(arbitration_id=0x190, is_remote_frame=True, dlc=8, is_extended_id=False),
              can.Message(arbitration_id=0x190, data=raw + bytes(8), is_fd=True, is_extended_id=False),
              can.Message(arbitration_id=0x4, is_error_frame=True),
              can.Message(arbitration_id=0x290, data=bytes(3), is_extended_id=False)]
    for k, fault in enumerate(faults):  # spread over the stream, timestamps in order
        at = (k + 1) * len(msgs) // (len(faults) + 2)
        fault.timestamp = msgs[at].timestamp
        msgs.insert(at, fault)
    return msgs


def test_compiled_daemon_sends_what_the_reference_sends(folder: Path) -> None:
    config = load_config(write_config(folder, "cmp"))
    msgs = stream_with_faults(600)
    half = len(msgs) // 2
    reference, compiled = Daemon(config, compiled=False), Daemon(config)
    sent_ref: list[bytes] = []

    class RefBus:
        def send(self, msg: can.Message, timeout: float | None = None) -> None:
            sent_ref.append(bytes(msg.data))

    for daemon in (reference, compiled):
        daemon.load_sets()
    feed(reference, msgs[:half], RefBus())
    sock = StandInSocket(compiled, [(kernel_frame(m), m.timestamp) for m in msgs[:half]])
    serve_socket(compiled, sock)

    for axis in ("x", "y", "z"):  # new sets for every axis, adopted between two frames
        text = (folder / "next" / f"imu-{axis}.yaml").read_text()
        atomic_file.write_text_atomic(folder / f"imu-{axis}.yaml", text)
    for daemon in (reference, compiled):
        daemon._running = True
        daemon._reload(force=False, why="test")
    assert compiled.sets.combined_id == reference.sets.combined_id != 0
    feed(reference, msgs[half:])
    sock.frames = iter([(kernel_frame(m), m.timestamp) for m in msgs[half:]])
    serve_socket(compiled, sock)

    assert len(sock.sent) == len(sent_ref) == 600
    assert sock.sent == sent_ref
    assert compiled.stats.as_dict() == reference.stats.as_dict()
    s = compiled.stats
    assert (s.bad_length, s.unknown_ids, s.remote_frames, s.fd_frames, s.error_frames) == (2, 2, 1, 1, 1)
    assert {a.axis: len(a.corrector.terms) for a in compiled.sets.axes} == {"x": 2, "y": 2, "z": 2}
    # every axis compiled
    assert all(getattr(a.correct, "source", None) for a in compiled.raw_path.plans.current.axes)


def test_full_transmit_queue_drops_and_counts(folder: Path) -> None:
    daemon = Daemon(load_config(write_config(folder, "full")))
    daemon.load_sets()
    msgs = [m for m in stream_with_faults(20) if m.arbitration_id == 0x190 and len(m.data) == 8
            and not m.is_remote_frame and not m.is_extended_id and not m.is_fd]
    sock = StandInSocket(daemon, [(kernel_frame(m), m.timestamp) for m in msgs])
    sock.full = True
    serve_socket(daemon, sock)
    assert (daemon.stats.frames_in, daemon.stats.tx_dropped, len(sock.sent)) == (20, 20, 0)


def test_frame_layout_is_the_kernels() -> None:
    """<linux/can.h>: struct can_frame is 16 bytes, can_id native-endian, data from byte 8."""
    assert FRAME_HEAD.size == 8 and struct.calcsize("=IBB1xB8s") == 16
