"""What the daemon reports about itself: its counters, the status frame's pages, systemd STATUS.

The counters are plain integers the frame path increments (a slotted object: an attribute
increment is the cheapest count there is); the pages and the status line are built from them
between frames, at the status period.
"""

from __future__ import annotations

from collections.abc import Iterable, Mapping

from canical.bus.active_sets import ActiveSets
from canical.bus.socketcan import socket_frame
from canical.bus_outage import Outage
from canical.frames.codec import StatusEncoder

__all__ = ["AXIS_CODES", "SATURATING_PAGES", "STATE_DEGRADED", "STATE_NAMES", "STATE_RUNNING",
           "STATE_STARTING", "STATE_STOPPING", "Stats", "status_frames", "status_line", "status_pages"]

#: The daemon's state, as the status frame's ``State`` signal carries it.
STATE_STARTING, STATE_RUNNING, STATE_DEGRADED, STATE_STOPPING = 0, 1, 2, 3
STATE_NAMES = ("starting", "running", "degraded", "stopping")
AXIS_CODES = {"x": 0, "y": 1, "z": 2}
#: Status pages whose counters stop at their maximum (fault counts: 255 means "255 or more");
#: page 0's frame counters are rolling and wrap, so receivers can take differences.
SATURATING_PAGES = frozenset({2})


class Stats:
    """Counters for the status frame and systemd STATUS (they only ever grow)."""

    __slots__ = ("bad_length", "bus_restarts", "counter_gaps", "error_frames", "fd_frames",
                 "frames_in", "frames_out", "inputs_in", "remote_frames", "stale_frames",
                 "tx_dropped", "unknown_ids")
    # Declared for the type checker; __init__ sets each slot to 0.
    bad_length: int
    bus_restarts: int
    counter_gaps: int
    error_frames: int
    fd_frames: int
    frames_in: int
    frames_out: int
    inputs_in: int
    remote_frames: int
    stale_frames: int
    tx_dropped: int
    unknown_ids: int

    def __init__(self) -> None:
        for name in self.__slots__:
            setattr(self, name, 0)

    @property
    def bad(self) -> int:
        return self.bad_length + self.unknown_ids + self.remote_frames + self.fd_frames

    def as_dict(self) -> dict[str, int]:
        return {name: getattr(self, name) for name in self.__slots__}


BIAS_PAGE = 3  # the page of each axis's learned bias (canical.bus.bias_tracking)


def status_frames(status: StatusEncoder, pages: list[tuple[int, dict[str, int]]],
                  bias: Iterable[Mapping[str, float]] | None) -> list[bytes]:
    """The status frame's pages as kernel frames: the counters' pages, then (with ``bias``, the
    bias tracking's pages, when the DBC's status frame has the page) each axis's learned bias."""
    frames = [status.encode(page, values, saturate=page in SATURATING_PAGES) for page, values in pages]
    if bias is not None and BIAS_PAGE in status.pages:
        frames += [status.encode_physical(BIAS_PAGE, dict(b)) for b in bias]
    return [socket_frame(status.frame_id, status.is_extended, payload) for payload in frames]


def status_pages(state: int, stats: Stats, sets: ActiveSets,
                 pages: tuple[int, ...]) -> list[tuple[int, dict[str, int]]]:
    """The status frame's pages: counters, one page per axis set, fault counters (when the
    DBC's status frame has ``pages`` 2)."""
    s = stats
    out = [(0, {"State": state, "FramesIn": s.frames_in, "FramesOut": s.frames_out,
                "FramesBad": s.bad, "CounterGaps": s.counter_gaps, "BusErrors": s.error_frames})]
    for ax in sets.axes:
        out.append((1, {"SetAxis": AXIS_CODES[ax.axis], "SetId": ax.set_id, "SetTag": sets.tag,
                        "SetSource": ax.source, "Reloads": ax.reloads}))
    if 2 in pages:
        out.append((2, {"BadLength": s.bad_length, "UnknownIds": s.unknown_ids,
                        "RemoteFrames": s.remote_frames, "FdFrames": s.fd_frames,
                        "BusRestarts": s.bus_restarts, "StaleFrames": s.stale_frames,
                        "TxDropped": s.tx_dropped}))
    return out


def status_line(state: int, stats: Stats, sets: ActiveSets, *, channel: str, outage: Outage | None,
                now: float) -> str:
    """systemd's STATUS: the state (and an ongoing outage), the counters, the sets in use."""
    s = stats
    text = STATE_NAMES[state]
    if outage is not None:
        text = f"{text}, {channel} down for {now - outage.since:.0f} s ({outage.reason})"
    return (f"{text}: {s.frames_in} frames in, {s.frames_out} out, {s.bad} bad, "
            f"{s.counter_gaps} gaps, {s.error_frames} error frames, {s.bus_restarts} bus restarts; "
            f"sets {sets.describe()}")
