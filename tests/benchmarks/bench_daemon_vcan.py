"""End to end on vcan: the daemon against a bare python-can forwarder, in the same kernel.

Both subjects run as separate processes on vcan0: the forwarder receives the raw frame (same
kernel filter) and sends its payload unchanged as the corrected frame's id; the daemon
decodes, corrects and encodes. For each, this script

* offers N raw frames as fast as one raw-socket sender can (throughput and loss), and
* offers frames paced at a series of rates (loss at each; latency from raw frame to output
  frame, both timestamped by the kernel at one receiving socket: median and p99).

It prints the daemon's figures as a ratio of the forwarder's. On a host without SocketCAN it
re-runs itself inside a User-mode Linux guest (one CPU, slow system calls: absolute figures
there are the guest's, the ratio is the point).

    python tests/benchmarks/bench_daemon_vcan.py [--frames N] [--rates 500,1000,...]
"""

from __future__ import annotations

import argparse
import os
import socket
import statistics
import struct
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TESTS = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(TESTS))

import vcan_harness  # noqa: E402

CHANNEL = "vcan0"
RAW_ID, OUT_ID, AUX_ID = 0x190, 0x110, 0x290
FRAME = struct.Struct("=IB3x8s")
SO_RCVBUFFORCE = 33
SO_TIMESTAMPNS = 35

FORWARDER = f"""
import can, sys
bus = can.Bus(interface="socketcan", channel="{CHANNEL}",
              can_filters=[{{"can_id": {RAW_ID}, "can_mask": 0x7FF, "extended": False}}])
print("ready", flush=True)
while True:
    m = bus.recv()
    if m is not None:
        bus.send(can.Message(arbitration_id={OUT_ID}, data=m.data, is_extended_id=False))
"""


def receiver() -> socket.socket:
    """A raw socket that keeps everything (big buffer) with kernel receive timestamps."""
    s = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    s.setsockopt(socket.SOL_SOCKET, SO_RCVBUFFORCE, 256 << 20)
    s.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
    mask = 0x7FF | socket.CAN_EFF_FLAG
    s.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER, struct.pack("=IIII", RAW_ID, mask, OUT_ID, mask))
    s.bind((CHANNEL,))
    return s


def drain(s: socket.socket, quiet_s: float = 1.5) -> list[tuple[int, float]]:
    """(id, kernel timestamp) of everything received until nothing came for ``quiet_s``."""
    out = []
    s.settimeout(quiet_s)
    while True:
        try:
            data, anc, _, _ = s.recvmsg(16, 64)
        except TimeoutError:
            return out
        can_id = FRAME.unpack(data)[0] & 0x7FF
        sec, nsec = struct.unpack("=qq", anc[0][2][:16])
        out.append((can_id, sec + nsec * 1e-9))


def send_all(frames: list[bytes], rate_hz: float | None) -> float:
    """Send pre-packed frames (as fast as possible, or paced); returns the achieved rate."""
    tx = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
    tx.bind((CHANNEL,))
    start = time.perf_counter()
    for i, f in enumerate(frames):
        while True:
            try:
                tx.send(f)
                break
            except OSError:  # ENOBUFS: the queue is full, give the receivers a moment
                time.sleep(0.0002)
        if rate_hz:  # each frame on its own schedule: bursts would queue and look like latency
            lag = start + (i + 1) / rate_hz - time.perf_counter()
            if lag > 0:
                time.sleep(lag)
    elapsed = time.perf_counter() - start
    tx.close()
    return len(frames) / elapsed


def measure(frames: list[bytes], rate_hz: float | None) -> dict[str, float]:
    rx = receiver()
    sent_rate = send_all(frames, rate_hz)
    got = drain(rx)
    rx.close()
    raws = [t for i, t in got if i == RAW_ID]
    outs = [t for i, t in got if i == OUT_ID]
    result = {"offered_fps": sent_rate, "sent": len(raws), "out": len(outs),
              "loss": 1.0 - len(outs) / max(len(raws), 1)}
    if len(outs) > 1:
        result["throughput_fps"] = len(outs) / (outs[-1] - raws[0])
    if len(outs) == len(raws):  # no loss: the i-th output answers the i-th raw frame
        lat = sorted(o - r for r, o in zip(raws, outs, strict=True))
        result["lat_median_us"] = statistics.median(lat) * 1e6
        result["lat_p99_us"] = lat[int(0.99 * (len(lat) - 1))] * 1e6
    return result


def start_daemon(folder: Path):
    from daemon_fixtures import DaemonProcess, write_config, write_sets

    write_sets(folder)
    return DaemonProcess(write_config(folder, CHANNEL), watchdog_usec=5_000_000)


def start_forwarder():
    proc = subprocess.Popen([sys.executable, "-c", FORWARDER], stdout=subprocess.PIPE, text=True)
    assert proc.stdout is not None and proc.stdout.readline().strip() == "ready"
    return proc


def run(args: argparse.Namespace) -> None:
    from daemon_fixtures import imu_stream

    stream = imu_stream(max(args.frames, args.paced_frames), rate_limit_dps=50.0)
    raw = [FRAME.pack(fid, len(d), d) for fid, d in stream.frames if fid == RAW_ID]
    blast, paced = raw[: args.frames], raw[: args.paced_frames]
    rates = [float(r) for r in args.rates.split(",")]
    results: dict[str, dict] = {}
    for name in ("forwarder", "daemon"):
        folder = Path(tempfile.mkdtemp(prefix=f"bench-{name}-"))
        subject = start_forwarder() if name == "forwarder" else start_daemon(folder)
        try:
            time.sleep(0.5)
            measure(raw[:200], 1000.0)  # warm-up
            results[name] = {"paced": {r: measure(paced, r) for r in rates}, "blast": measure(blast, None)}
        finally:
            if name == "forwarder":
                subject.terminate()
                subject.wait()
            else:
                subject.stop()
    where = "UML guest, 1 CPU" if os.environ.get(vcan_harness.ENV_IN_UML) == "1" else "host kernel"
    print(f"end to end on {CHANNEL} ({where}; Python {sys.version.split()[0]}); sender, subject and "
          "receiver share the machine")
    print(f"  paced, {args.paced_frames} raw frames per rate (latency: raw frame -> output frame, "
          "kernel timestamps at one socket)")
    for rate in rates:
        for name in results:
            p = results[name]["paced"][rate]
            lat = (f"latency median {p['lat_median_us']:7.0f} µs  p99 {p['lat_p99_us']:7.0f} µs"
                   if "lat_median_us" in p else "latency n/a (frames lost)")
            print(f"    {rate:6.0f}/s (got {p['offered_fps']:5.0f}) {name:9s}: "
                  f"out {p['out']:5d} of {p['sent']:5d}, loss {100 * p['loss']:5.1f} %, {lat}")
    print(f"  saturated: {args.frames} raw frames as fast as a raw socket sends them")
    for name in results:
        b = results[name]["blast"]
        print(f"    {name:9s}: offered {b['offered_fps']:8,.0f}/s, out {b['out']:6d} of {b['sent']}, "
              f"throughput {b.get('throughput_fps', 0):7,.0f} frames/s, loss {100 * b['loss']:5.1f} %")

    def lossless(name: str) -> float:
        ok = [r for r in rates if results[name]["paced"][r]["loss"] <= 0.001]
        return max(ok) if ok else 0.0

    f, d = results["forwarder"], results["daemon"]
    first = rates[0]
    lat = ""
    if "lat_median_us" in d["paced"][first] and "lat_median_us" in f["paced"][first]:
        lat = (f"; median latency at {first:.0f}/s {d['paced'][first]['lat_median_us']:.0f} vs "
               f"{f['paced'][first]['lat_median_us']:.0f} µs")
    print(f"  daemon / forwarder: saturated throughput "
          f"{d['blast'].get('throughput_fps', 0) / f['blast']['throughput_fps']:.2f}, "
          f"highest lossless rate tried {lossless('daemon'):.0f} vs {lossless('forwarder'):.0f} "
          f"frames/s{lat}")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20_000, help="frames offered as fast as possible")
    parser.add_argument("--paced-frames", type=int, default=2_000, help="frames per paced rate")
    parser.add_argument("--rates", default="250,1000,2000,3000,4000,6000",
                        help="paced rates to offer, frames/s")
    args = parser.parse_args()
    status = vcan_harness.run_script_on_vcan()
    if status is not None:
        return status
    run(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
