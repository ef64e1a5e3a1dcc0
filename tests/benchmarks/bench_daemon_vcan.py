"""End to end on vcan: the daemon against a bare python-can forwarder, in the same kernel, same run.

Subjects run one at a time as separate processes on vcan0, in turn, for ``--rounds`` rounds
(so all of them see the same machine): the forwarder receives the raw frame (same kernel
filter) with python-can and sends its payload unchanged as the corrected frame's id; the raw
forwarder does the same with one ``recvmsg`` and one ``send`` on a raw socket and nothing else
(the floor of any frame path here: what the guest's system calls cost); the daemon decodes,
corrects (effect terms on all three axes) and encodes; with ``--baseline DIR`` also the daemon
of another source tree (e.g. ``git archive`` of an older commit), for a before/after table.
For each subject this script

* offers frames paced at a series of rates (loss at each; latency from raw frame to output
  frame, both timestamped by the kernel at one receiving socket: median and p99; the
  subject's CPU time per wall second over the phase, from the kernel's accounting of the
  process, ``/proc/PID/stat`` utime + stime, what ``getrusage`` reports for a process), and
* offers N raw frames as fast as one raw-socket sender can (saturated throughput, loss, CPU);
  CPU is also the scheduler's run time (``/proc/PID/task/*/schedstat``), which in this kernel
  is what utime + stime add up to (they are that total split in the ticks' proportions);
* for the daemons: exec to READY=1 and resident memory after start (VmRSS) and at the end
  (VmHWM).

It prints the figures and each daemon's ratios to the forwarder's. On a host without SocketCAN
it re-runs itself inside a User-mode Linux guest (one CPU, slow system calls: absolute figures
there are the guest's, the ratios are the point).

    python tests/benchmarks/bench_daemon_vcan.py [--frames N] [--rates 200,1000,...] [--rounds N]
        [--baseline DIR] [--quick]
"""

from __future__ import annotations

import argparse
import os
import shutil
import signal
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

from support import vcan_harness  # noqa: E402

CHANNEL = "vcan0"
RAW_ID, OUT_ID, AUX_ID = 0x190, 0x110, 0x290
FRAME = struct.Struct("=IB3x8s")
SO_RCVBUFFORCE = 33
SO_TIMESTAMPNS = 35
TICK = os.sysconf("SC_CLK_TCK")

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

#: The floor: one recvmsg and one send per frame on a raw socket, nothing else (what the
#: daemon's frame path does around its Python work), to tell the guest's system-call cost apart.
RAW_FORWARDER = f"""
import socket, struct
s = socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW)
only_raw = struct.pack("=II", {RAW_ID}, 0x7FF | socket.CAN_EFF_FLAG)
s.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER, only_raw)
s.setsockopt(socket.SOL_SOCKET, 35, 1)  # kernel timestamps, as the daemon asks for
s.bind(("{CHANNEL}",))
out = struct.pack("=IB3x", {OUT_ID}, 8)
print("ready", flush=True)
while True:
    cf, anc, _, _ = s.recvmsg(72, 64)
    try:
        s.send(out + cf[8:16], socket.MSG_DONTWAIT)
    except OSError:
        pass
"""


def cpu_seconds(pid: int) -> float:
    """User + system CPU time of a process so far (the kernel's accounting, as getrusage).

    In the UML guest this is tick-sampled (``CONFIG_TICK_CPU_ACCOUNTING``, ``HZ=100``): each
    10 ms tick charges the whole tick to whichever task it interrupts. A task that wakes for a
    frame and sleeps again within a tick is charged by chance: over a few seconds at 1 %
    of a core that is a handful of ticks, and the paced sender, waking on the same timer,
    shifts which task the tick finds. :func:`run_seconds` is the measured form.
    """
    fields = Path(f"/proc/{pid}/stat").read_text().rsplit(")", 1)[1].split()
    return (int(fields[11]) + int(fields[12])) / TICK


def run_seconds(pid: int) -> float:
    """Time the scheduler measured the process's threads on the CPU (``/proc/PID/task/*/schedstat``,
    first field, ns: ``CONFIG_SCHED_INFO``'s clock, read at every switch, not sampled).

    In the UML guest the scheduler's clock is the host's: a task's run time includes the time
    the host took the whole guest away while that task was current (on a loaded host, more).
    """
    total = 0
    for task in Path(f"/proc/{pid}/task").iterdir():
        with open(task / "schedstat") as f:  # a thread that ended meanwhile: counted up to then
            total += int(f.read().split()[0])
    return total * 1e-9


def memory_kb(pid: int, key: str) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith(key + ":"):
            return int(line.split()[1])
    return 0


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


def send_all(frames: list[bytes], rate_hz: float | None) -> tuple[float, float]:
    """Send pre-packed frames (as fast as possible, or paced); the achieved rate and the time taken."""
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
    return len(frames) / elapsed, elapsed


def measure(frames: list[bytes], rate_hz: float | None, pid: int) -> dict[str, float]:
    rx = receiver()
    cpu0, run0, wall0 = cpu_seconds(pid), run_seconds(pid), time.monotonic()
    sent_rate, _ = send_all(frames, rate_hz)
    got = drain(rx, quiet_s=0.3)
    rx.settimeout(1.2)
    got += drain(rx)
    # the quiet tail is not the subject's work (it sleeps in recvmsg: no run time, no ticks)
    cpu1, run1, wall1 = cpu_seconds(pid), run_seconds(pid), time.monotonic() - 1.5
    rx.close()
    raws = [t for i, t in got if i == RAW_ID]
    outs = [t for i, t in got if i == OUT_ID]
    result = {"offered_fps": sent_rate, "sent": len(raws), "out": len(outs),
              "loss": 1.0 - len(outs) / max(len(raws), 1),
              "cpu": (cpu1 - cpu0) / max(wall1 - wall0, 1e-3),
              "run": (run1 - run0) / max(wall1 - wall0, 1e-3),
              "ticks": round((cpu1 - cpu0) * TICK), "run_s": run1 - run0}
    if len(outs) > 1:
        result["throughput_fps"] = len(outs) / (outs[-1] - raws[0])
    if len(outs) == len(raws):  # no loss: the i-th output answers the i-th raw frame
        lat = sorted(o - r for r, o in zip(raws, outs, strict=True))
        result["lat_median_us"] = statistics.median(lat) * 1e6
        result["lat_p99_us"] = lat[int(0.99 * (len(lat) - 1))] * 1e6
    return result


class Subject:
    """One process under test: the forwarder, or a daemon (this tree's, or a baseline's)."""

    def __init__(self, name: str, baseline: str | None = None) -> None:
        self.name, self.baseline = name, baseline
        self.proc = self.daemon = None
        self.start: dict[str, float] = {}

    def __enter__(self) -> Subject:
        if self.name in ("forwarder", "raw-forwarder"):
            script = FORWARDER if self.name == "forwarder" else RAW_FORWARDER
            self.proc = subprocess.Popen([sys.executable, "-c", script], stdout=subprocess.PIPE, text=True)
            assert self.proc.stdout is not None and self.proc.stdout.readline().strip() == "ready"
            self.pid = self.proc.pid
            return self
        from support.daemon_fixtures import ALL_TERMS, DaemonProcess, write_config, write_sets

        folder = Path(tempfile.mkdtemp(prefix=f"bench-{self.name}-"))
        write_sets(folder, terms=ALL_TERMS)
        # PYTHONSAFEPATH: "-m canical" must not find this tree's package in its working directory
        env = {"PYTHONPATH": self.baseline, "PYTHONSAFEPATH": "1"} if self.baseline else None
        self.daemon = DaemonProcess(write_config(folder, CHANNEL), watchdog_usec=5_000_000, extra_env=env)
        self.pid = self.daemon.proc.pid
        self.start = {"ready_s": self.daemon.notify.arrived["READY"] - self.daemon.started,
                      "rss_kb": memory_kb(self.pid, "VmRSS")}
        return self

    def syscalls(self, frames: list[bytes], rate_hz: float | None) -> dict[str, float]:
        """System calls per frame handled (``strace -c`` attached to every thread meanwhile).

        Tracing slows the subject down so much that it drops frames: counts are divided by
        the frames it received (its ``recvmsg`` calls), not by the frames sent.
        """
        out = Path(tempfile.mkdtemp(prefix="bench-strace-")) / "summary"
        tracer = subprocess.Popen(["strace", "-c", "-f", "-p", str(self.pid), "-o", str(out)],
                                  stderr=subprocess.DEVNULL)
        time.sleep(1.0)  # attached
        measure(frames, rate_hz, self.pid)
        tracer.send_signal(signal.SIGINT)
        tracer.wait()
        calls: dict[str, int] = {}
        for line in out.read_text().splitlines():
            parts = line.split()
            if len(parts) >= 5 and parts[3].isdigit() and parts[-1] != "total":
                calls[parts[-1]] = int(parts[3])
        handled = max(calls.get("recvmsg", 0), 1)
        return {name: n / handled for name, n in calls.items()}

    def __exit__(self, *exc) -> None:
        if self.daemon is not None:
            self.start["hwm_kb"] = memory_kb(self.pid, "VmHWM")
            self.daemon.stop()
        elif self.proc is not None:
            self.proc.terminate()
            self.proc.wait()


def run(args: argparse.Namespace) -> None:
    from support.daemon_fixtures import imu_stream

    rates = [float(r) for r in args.rates.split(",")]
    per_rate = {r: max(args.paced_frames, int(r * args.paced_seconds)) for r in rates}
    stream = imu_stream(max(args.frames, *per_rate.values()), rate_limit_dps=50.0)
    raw = [FRAME.pack(fid, len(d), d) for fid, d in stream.frames if fid == RAW_ID]
    names = ["forwarder", "daemon"] + (["daemon-before"] if args.baseline else []) + ["raw-forwarder"]
    runs: dict[str, list[dict]] = {n: [] for n in names}
    for _ in range(args.rounds):
        for name in names:
            with Subject(name, args.baseline if name == "daemon-before" else None) as subject:
                time.sleep(0.5)
                measure(raw[:200], 1000.0, subject.pid)  # warm-up
                paced = {r: measure(raw[: per_rate[r]], r, subject.pid) for r in rates}
                blast = measure(raw[: args.frames], None, subject.pid)
                traced = (subject.syscalls(raw[: per_rate[args.strace_rate]], args.strace_rate)
                          if args.strace_rate and shutil.which("strace") else None)
            runs[name].append({"paced": paced, "blast": blast, "syscalls": traced, **subject.start})
    where = "UML guest, 1 CPU" if os.environ.get(vcan_harness.ENV_IN_UML) == "1" else "host kernel"
    print(f"end to end on {CHANNEL} ({where}; Python {sys.version.split()[0]}); sender, subject and "
          f"receiver share the machine; {args.rounds} round(s), subjects in turn; ranges over rounds")

    def span(values: list[float], fmt: str) -> str:
        lo, hi = min(values), max(values)
        return format(lo, fmt) if f"{lo:{fmt}}" == f"{hi:{fmt}}" else f"{lo:{fmt}}–{hi:{fmt}}"

    print("  paced: loss %, latency raw -> output median / p99 µs (kernel timestamps), CPU % of a core")
    for rate in rates:
        for name in names:
            ps = [r["paced"][rate] for r in runs[name]]
            lat = [p for p in ps if "lat_median_us" in p]
            text = (f"median {span([p['lat_median_us'] for p in lat], '.0f')}  "
                    f"p99 {span([p['lat_p99_us'] for p in lat], '.0f')}" if lat else "latency n/a (loss)")
            print(f"    {rate:6.0f}/s {name:13s}: loss {span([100 * p['loss'] for p in ps], '.1f')} %, "
                  f"{text}, CPU {span([100 * p['run'] for p in ps], '.2f')} % run time, "
                  f"{span([100 * p['cpu'] for p in ps], '.1f')} % ticks  ({ps[0]['sent']} frames)")
    print(f"  saturated: {args.frames} raw frames as fast as a raw socket sends them")
    for name in names:
        bs = [r["blast"] for r in runs[name]]
        fps = span([b.get("throughput_fps", 0) for b in bs], ",.0f")
        loss, cpu = span([100 * b["loss"] for b in bs], ".1f"), span([100 * b["cpu"] for b in bs], ".0f")
        run_ = span([100 * b["run"] for b in bs], ".0f")
        print(f"    {name:13s}: throughput {fps} frames/s, loss {loss} %, "
              f"CPU {run_} % run time, {cpu} % ticks")
    daemons = [n for n in names if n.startswith("daemon")]
    for name in daemons:
        rs = runs[name]
        rss, hwm = [r["rss_kb"] / 1024 for r in rs], [r["hwm_kb"] / 1024 for r in rs]
        print(f"  {name}: exec -> READY=1 {span([r['ready_s'] for r in rs], '.2f')} s, resident after start "
              f"{span(rss, '.1f')} MB, peak {span(hwm, '.1f')} MB")

    if runs[names[0]][0]["syscalls"] is not None:
        print(f"  system calls per frame handled at {args.strace_rate:.0f}/s (strace -c, every thread; "
              "last round)")
        for name in names:
            calls = runs[name][-1]["syscalls"]
            top = sorted(calls.items(), key=lambda kv: -kv[1])
            print(f"    {name:13s}: {sum(calls.values()):5.2f}  ("
                  + ", ".join(f"{k} {v:.2f}" for k, v in top if v >= 0.01) + ")")

    def lossless(name: str, k: int) -> float:
        ok = [r for r in rates if runs[name][k]["paced"][r]["loss"] <= 0.001]
        return max(ok) if ok else 0.0

    for name in daemons:
        ratios, p99 = [], []
        for k in range(args.rounds):
            f, d = runs["forwarder"][k], runs[name][k]
            ratios.append(d["blast"].get("throughput_fps", 0) / max(f["blast"].get("throughput_fps", 0), 1.0))
            for rate in rates:
                fp, dp = f["paced"][rate], d["paced"][rate]
                if "lat_p99_us" in fp and "lat_p99_us" in dp:
                    p99.append(dp["lat_p99_us"] / fp["lat_p99_us"])
        lossless_d = [lossless(name, k) for k in range(args.rounds)]
        lossless_f = [lossless("forwarder", k) for k in range(args.rounds)]
        print(f"  {name} / forwarder: saturated throughput {span(ratios, '.2f')}; highest lossless rate "
              f"{span(lossless_d, '.0f')} vs {span(lossless_f, '.0f')} frames/s; p99 latency ratio where "
              f"both lossless {span(p99, '.2f') if p99 else 'n/a'}")
    table(runs, names, rates, args.rounds, lossless)


def table(runs: dict[str, list[dict]], names: list[str], rates: list[float], rounds: int, lossless) -> None:
    """The figures above as one Markdown table, subjects as columns (ranges over rounds)."""

    def span(values: list[float], fmt: str) -> str:
        if not values:
            return "n/a"
        lo, hi = min(values), max(values)
        return format(lo, fmt) if f"{lo:{fmt}}" == f"{hi:{fmt}}" else f"{lo:{fmt}}–{hi:{fmt}}"

    heads = {"forwarder": "python-can forwarder", "daemon": "after (this tree)",
             "daemon-before": "before (baseline)", "raw-forwarder": "raw recvmsg+send (floor)"}
    order = [n for n in ("forwarder", "daemon-before", "daemon", "raw-forwarder") if n in names]
    rows: list[tuple[str, dict[str, str]]] = []

    def row(label: str, cell) -> None:
        rows.append((label, {n: cell(n) for n in order}))

    row("saturated throughput, frames/s",
        lambda n: span([r["blast"].get("throughput_fps", 0) for r in runs[n]], ",.0f"))
    row("— ratio to the python-can forwarder's", lambda n: "" if n == "forwarder" else span(
        [d["blast"].get("throughput_fps", 0) / max(f["blast"].get("throughput_fps", 0), 1.0)
         for d, f in zip(runs[n], runs["forwarder"], strict=True)], ".2f"))
    row("highest lossless paced rate, /s", lambda n: span([lossless(n, k) for k in range(rounds)], ".0f"))
    for rate in rates:
        row(f"loss at {rate:.0f} /s, %",
            lambda n, rate=rate: span([100 * r["paced"][rate]["loss"] for r in runs[n]], ".1f"))
    for rate in rates:
        row(f"latency p99 at {rate:.0f} /s, µs", lambda n, rate=rate: span(
            [r["paced"][rate]["lat_p99_us"] for r in runs[n] if "lat_p99_us" in r["paced"][rate]], ".0f"))
    for rate in (*[r for r in rates if r in (200.0, 1000.0)], None):
        where = "saturated" if rate is None else f"{rate:.0f} /s"

        def phase(r: dict, rate=rate) -> dict:
            return r["blast"] if rate is None else r["paced"][rate]

        row(f"CPU per wall second, {where}: run time (schedstat), %",
            lambda n, phase=phase: span([100 * phase(r)["run"] for r in runs[n]], ".2f"))
        row(f"CPU per wall second, {where}: utime+stime (ticks), %",
            lambda n, phase=phase: span([100 * phase(r)["cpu"] for r in runs[n]], ".1f"))
    row("run time per raw frame, saturated, µs",
        lambda n: span([1e6 * r["blast"]["run_s"] / max(r["blast"]["sent"], 1) for r in runs[n]], ".0f"))

    def daemon_only(n: str, key: str, fmt: str, scale: float = 1.0) -> str:
        return "" if "forwarder" in n else span([r[key] * scale for r in runs[n]], fmt)

    row("exec -> READY=1, s", lambda n: daemon_only(n, "ready_s", ".2f"))
    row("resident after start, MB", lambda n: daemon_only(n, "rss_kb", ".1f", 1 / 1024))
    row("resident peak, MB", lambda n: daemon_only(n, "hwm_kb", ".1f", 1 / 1024))
    print()
    print("| figure | " + " | ".join(heads[n] for n in order) + " |")
    print("|---|" + "---|" * len(order))
    for label, cells in rows:
        print(f"| {label} | " + " | ".join(cells[n] for n in order) + " |")


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--frames", type=int, default=20_000, help="frames offered as fast as possible")
    parser.add_argument("--paced-frames", type=int, default=2_000, help="least frames per paced rate")
    parser.add_argument("--paced-seconds", type=float, default=5.0, help="least seconds per paced rate")
    parser.add_argument("--rates", default="200,1000,2000,3000,4000,6000", help="paced rates, frames/s")
    parser.add_argument("--rounds", type=int, default=2, help="rounds of all subjects in turn")
    parser.add_argument("--baseline", help="source tree of a daemon to compare (before/after)")
    parser.add_argument("--strace-rate", type=float, default=1000.0,
                        help="paced rate at which system calls are counted (0: not)")
    parser.add_argument("--quick", action="store_true", help="small sizes: checks the script runs")
    args = parser.parse_args()
    if args.quick:
        args.frames, args.paced_frames, args.paced_seconds = 300, 100, 0.1
        args.rates, args.rounds, args.strace_rate = "1000", 1, 0.0
    status = vcan_harness.run_script_on_vcan(timeout=3000.0)
    if status is not None:
        return status
    run(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
