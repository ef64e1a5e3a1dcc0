"""What verifying signatures (``trust:``) adds to a daemon reload: the reload worker's whole build
(read, validate, build correctors) of three signed per-axis sets and of one signed IMU set, with
and without ``trust: {require: true}``, and the Ed25519 verification alone. The issue's bound:
at most 5 ms more per reload; nothing is added per frame (verification is done at load).
Prints medians over rounds, the two configurations interleaved (a busy machine slows both alike).

    python tests/benchmarks/bench_reload_verify.py [--quick]
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from support.daemon_fixtures import ALL_TERMS, imu_set_config, write_config, write_imu_set, write_sets
from support.signed_sets import make_lab, signed_copy

from canical.bus import active_sets
from canical.bus.daemon_config import DaemonConfig, load_config
from canical.files.key_file import read_public
from canical.sets.signed_file import read_set_file
from canical.sets.signing import TrustedKey, verify

LIMIT_MS = 5.0


def signed_folder(folder: Path, lab_key: Path, *, imu: bool) -> Path:
    """A folder of signed sets (three per-axis sets, or one IMU set) as a daemon reads them."""
    folder.mkdir()
    staging = folder / "unsigned"
    staging.mkdir()
    if imu:
        signed_copy(write_imu_set(staging, terms=ALL_TERMS), folder / "imu-set.yaml", lab_key)
    else:
        for path in write_sets(staging, terms=ALL_TERMS).values():
            signed_copy(path, folder / path.name, lab_key)
    return folder


def configs(folder: Path, lab_pub: Path, *, imu: bool) -> tuple[DaemonConfig, DaemonConfig]:
    """The same daemon without and with ``trust: {keys: [lab.pub], require: true}``."""
    write = imu_set_config if imu else write_config
    trust = {"keys": [str(lab_pub)], "require": True}
    return load_config(write(folder, "plain")), load_config(write(folder, "trust", trust=trust))


def reload_ms(config: DaemonConfig) -> float:
    """One forced reload (SIGHUP) from no sets: every set read, verified, validated, built."""
    empty = active_sets.build(tuple(active_sets.AxisSet(a.axis, a.raw_signal,
                                                        path=config.imu_set or a.coefficients)
                                    for a in config.axes))
    t0 = time.perf_counter()
    sets, notes = active_sets.reload(config, empty, force=True)
    elapsed = (time.perf_counter() - t0) * 1e3
    assert sets.complete and not any(n.refused for n in notes), notes
    return elapsed


def median_ms(fn: Callable[[], float], rounds: int) -> float:
    return statistics.median(fn() for _ in range(rounds))


def verify_ms(path: Path, keys: tuple[TrustedKey, ...]) -> float:
    """The Ed25519 verification alone, over a set already read."""
    signed = read_set_file(path).signed
    t0 = time.perf_counter()
    verify(signed, keys, str(path))
    return (time.perf_counter() - t0) * 1e3


def main(rounds: int) -> None:
    root = Path(tempfile.mkdtemp(prefix="bench-reload-verify-"))
    lab = make_lab(root / "keys")
    keys = (TrustedKey(read_public(lab.pub), str(lab.pub)),)
    for imu in (False, True):
        what = "one IMU set" if imu else "three per-axis sets"
        folder = signed_folder(root / ("imu" if imu else "axes"), lab.key, imu=imu)
        plain, trusted = configs(folder, lab.pub, imu=imu)
        reload_ms(plain), reload_ms(trusted)  # warm: imports, the YAML parser, PyNaCl
        times: dict[str, list[float]] = {"plain": [], "trust": []}
        for _ in range(rounds):
            times["plain"].append(reload_ms(plain))
            times["trust"].append(reload_ms(trusted))
        without, with_ = statistics.median(times["plain"]), statistics.median(times["trust"])
        files = [folder / "imu-set.yaml"] if imu else sorted(folder.glob("imu-?.yaml"))
        alone = sum(median_ms(lambda p=p: verify_ms(p, keys), rounds) for p in files)
        added = with_ - without
        verdict = "within" if added <= LIMIT_MS else "OVER"
        print(f"{what}: reload {without:.2f} ms without trust:, {with_:.2f} ms with "
              f"(median of {rounds}); verification adds {added:+.2f} ms ({verdict} the {LIMIT_MS:g} ms "
              f"bound); Ed25519 alone {alone:.3f} ms for {len(files)} signature(s)")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes: checks the script runs")
    main(1 if parser.parse_args().quick else 25)
