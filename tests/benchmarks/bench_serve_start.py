"""Start-up of ``canical serve``: time from exec to READY=1, resident memory once ready.

Runs the real command as systemd would (a notify socket, a watchdog) on python-can's ``virtual``
interface, so it needs no CAN hardware and no guest: on this machine's own kernel. With
``--baseline DIR`` the daemon of another source tree runs in turn with this one (a before/after
table measured in the same run).

    python tests/benchmarks/bench_serve_start.py [--runs N] [--baseline DIR] [--quick]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from support.daemon_fixtures import ALL_TERMS, DaemonProcess, write_config, write_sets


def resident_kb(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    return 0


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--runs", type=int, default=5)
    parser.add_argument("--baseline", help="source tree of a daemon to compare (before/after)")
    parser.add_argument("--quick", action="store_true", help="small sizes: checks the script runs")
    args = parser.parse_args()
    if args.quick:
        args.runs = 1
    folder = Path(tempfile.mkdtemp(prefix="canical-start-"))
    write_sets(folder, terms=ALL_TERMS)
    config = write_config(folder, "bench", interface="virtual")
    # PYTHONSAFEPATH: "-m canical" must not find this tree's package in its working directory
    baseline = {"baseline": {"PYTHONPATH": args.baseline, "PYTHONSAFEPATH": "1"}} if args.baseline else {}
    subjects = {"this tree": None, **baseline}
    figures: dict[str, list[tuple[float, float]]] = {name: [] for name in subjects}
    for _ in range(args.runs):
        for name, env in subjects.items():
            daemon = DaemonProcess(config, watchdog_usec=5_000_000, extra_env=env)
            try:
                ready_s = daemon.notify.arrived["READY"] - daemon.started
                time.sleep(0.3)
                figures[name].append((ready_s, resident_kb(daemon.proc.pid) / 1024))
            finally:
                daemon.stop()
    print(f"canical serve start-up, {args.runs} runs each in turn (virtual bus; "
          f"Python {sys.version.split()[0]})")
    for name, runs in figures.items():
        ready, rss = [r for r, _ in runs], [m for _, m in runs]
        print(f"  {name:10s}: exec -> READY=1 {min(ready):.2f}–{max(ready):.2f} s (median "
              f"{statistics.median(ready):.2f}), resident after start {min(rss):.1f}–{max(rss):.1f} MB")


if __name__ == "__main__":
    main()
