"""Coefficient download over CANopen SDO: how long a full three-axis push takes, and how long from
the start of a push until corrected frames carry the new set (on the device, and in the daemon).

The emulated IMU runs as its own process on vcan0 (``canical emulate``, streaming raw frames at
``--rate`` with on-device correction on, so the bus carries a realistic load); this script pushes
alternating three-axis sets N times with :func:`canical.device.sdo_download.push_sets` and prints, per
phase, the median and worst time. "Push to corrected" is measured from the moment the push
starts to the first IMU_RATE frame tagged with the new sets (the device's TPDO3), and, with the
daemon (``device:`` in its configuration), to the first CANICAL_RATE frame tagged with them after
a SIGHUP sent when the push returns. On a host without SocketCAN the script re-runs itself inside
a User-mode Linux guest (one CPU, slow system calls: its absolute figures are the guest's).

    python tests/benchmarks/bench_imu_download.py [--pushes N] [--rate 100] [--quick]
"""

from __future__ import annotations

import argparse
import os
import signal
import statistics
import subprocess
import sys
import tempfile
import time
from pathlib import Path

TESTS = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(TESTS))

from support import vcan_harness  # noqa: E402

CHANNEL = "vcan0"
NODE = 0x10


def wait_ready(proc: subprocess.Popen[str], what: str, needle: str, timeout: float = 120.0) -> None:
    end = time.monotonic() + timeout
    while time.monotonic() < end:
        line = proc.stdout.readline()  # type: ignore[union-attr]
        if needle in line:
            return
        if not line and proc.poll() is not None:
            break
    raise SystemExit(f"{what} did not start")


def run(args: argparse.Namespace) -> None:
    import can
    import yaml
    from support.imu_fixtures import SERIAL, imu_sets

    from canical.device.bank_payload import encode_set
    from canical.device.can_network import network_on, sdo_client_filters
    from canical.device.sdo_download import ImuClient, push_sets
    from canical.frames.imu_dictionary import AXES
    from canical.frames.imu_frames import ImuFrames, set_tag
    from canical.sets import coefficient_file
    from canical.sets.coefficient_file import set_crc

    work = Path(tempfile.mkdtemp(prefix="bench-imu-"))
    families = [imu_sets(0), imu_sets(1)]
    tags = [set_tag({a: set_crc(f[a]) for a in AXES}) for f in families]
    assert tags[0] != tags[1], "the two families share a set tag: pick other seeds"
    size = sum(len(encode_set(c)[0]) for c in families[0].values())
    emulator = subprocess.Popen(
        [sys.executable, "-m", "canical", "emulate", "--interface", "socketcan", "--channel", CHANNEL,
         "--node", hex(NODE), "--serial", str(SERIAL), "--state", str(work / "imu.json"),
         "--rate", str(args.rate), "--table", "constant", "--correct"],
        stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, text=True)
    daemon = None
    try:
        wait_ready(emulator, "emulator", "ready")
        # The daemon, configured to take its sets from the device (files: family 1 as fallback).
        from support.daemon_fixtures import write_config

        for axis, cset in families[1].items():
            coefficient_file.save(work / f"imu-{axis}.yaml", cset)
        config = write_config(work, CHANNEL, sensor=str(SERIAL), device={"node": NODE, "timeout_s": 1.0})
        content = yaml.safe_load(config.read_text())
        config.write_text(yaml.safe_dump(content, sort_keys=False))
        frames = ImuFrames(NODE)
        rate_ids = [frames.ids["IMU_RATE"], 0x110]
        listen = can.Bus(interface="socketcan", channel=CHANNEL,
                         can_filters=[{"can_id": i, "can_mask": 0x7FF} for i in rate_ids])
        log = work / "daemon.log"
        with log.open("w") as out:
            daemon = subprocess.Popen([sys.executable, "-m", "canical", "serve", "--config", str(config)],
                                      stdout=out, stderr=subprocess.STDOUT, text=True)
        end = time.monotonic() + 120
        while "ready on" not in log.read_text() and time.monotonic() < end and daemon.poll() is None:
            time.sleep(0.2)  # its start reads the device over SDO: no push may overlap that
        if "ready on" not in log.read_text():
            raise SystemExit(f"daemon did not start: {log.read_text()[-2000:]}")
        phases: dict[str, list[float]] = {}
        to_device: list[float] = []
        to_daemon: list[float] = []
        with network_on("socketcan", CHANNEL, can_filters=sdo_client_filters(NODE)) as network:
            client = ImuClient(network, NODE, 1.0)
            for i in range(args.pushes):
                sets = families[i % 2]  # the daemon starts on family 1 (its files): first push differs
                tag = set_tag({a: set_crc(sets[a]) for a in AXES})
                while listen.recv(0) is not None:
                    pass
                t0 = time.monotonic()
                try:
                    result = push_sets(client, {a: (a, c) for a, c in sets.items()})
                except Exception as exc:
                    print(f"push {i}: {exc}\n--- daemon log ---\n{log.read_text()[-3000:]}")
                    raise
                t_done = time.monotonic()
                daemon.send_signal(signal.SIGHUP)
                for phase, seconds in result.timings_s.items():
                    phases.setdefault(phase, []).append(seconds)
                seen_device = seen_daemon = None
                end = time.monotonic() + 30
                while (seen_device is None or seen_daemon is None) and time.monotonic() < end:
                    msg = listen.recv(0.5)
                    if msg is None:
                        continue
                    if msg.data[7] & 0x0F != tag:  # SetTag, bits 56-59 of IMU_RATE and CANICAL_RATE
                        continue
                    if msg.arbitration_id == rate_ids[0] and seen_device is None:
                        seen_device = time.monotonic() - t0
                    daemon_frame = msg.arbitration_id == rate_ids[1] and time.monotonic() > t_done
                    if daemon_frame and seen_daemon is None:
                        seen_daemon = time.monotonic() - t0
                if seen_device is not None:
                    to_device.append(seen_device)
                if seen_daemon is not None:
                    to_daemon.append(seen_daemon)
        listen.shutdown()
    finally:
        for proc in (daemon, emulator):
            if proc is not None and proc.poll() is None:
                proc.terminate()
                proc.wait(20)

    where = "UML guest, 1 CPU" if os.environ.get(vcan_harness.ENV_IN_UML) == "1" else "host kernel"
    print(f"canical push, full three-axis set ({size} bytes of set content, "
          f"{size // 7 + 1} SDO segments, each a request and a response, to download and as many to "
          f"read back), {args.pushes} pushes on "
          f"{CHANNEL} ({where}), device streaming {args.rate:g} samples/s with on-device correction:")

    def line(name: str, values: list[float]) -> None:
        if values:
            print(f"  {name:40s} median {statistics.median(values) * 1000:8.1f} ms   "
                  f"max {max(values) * 1000:8.1f} ms   (n={len(values)})")
        else:
            print(f"  {name:40s} not observed")

    for phase in ("read_state", "download", "verify", "activate", "store", "total"):
        line(phase, phases.get(phase, []))
    line("push start -> device corrects (TPDO3)", to_device)
    line("push start -> daemon corrects (SIGHUP)", to_daemon)


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--pushes", type=int, default=10)
    parser.add_argument("--rate", type=float, default=100.0, help="raw samples/s the device streams")
    parser.add_argument("--quick", action="store_true", help="small sizes: checks the script runs")
    args = parser.parse_args()
    if args.quick:
        args.pushes = 1
    status = vcan_harness.run_script_on_vcan()
    if status is not None:
        return status
    run(args)
    return 0


if __name__ == "__main__":
    sys.exit(main())
