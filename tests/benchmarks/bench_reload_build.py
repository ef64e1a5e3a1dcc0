"""What a daemon reload costs off the frame thread: load and validate three coefficient sets
(what the reload worker does), then generate their correctors (done on the frame thread, on
the first frame of the new sets). Prints the median over rounds.

    python tests/benchmarks/bench_reload_build.py [--quick]  # here
    # in the UML guest (vcan tier's machine): tests/vcan_harness.run_in_uml([...this script...])
"""

from __future__ import annotations

import argparse
import statistics
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from support.daemon_fixtures import ALL_TERMS, write_config, write_sets

from canical.bus.active_sets import load_axis
from canical.bus.daemon_config import load_config
from canical.files import yaml_text
from canical.sets.fast_corrector import compile_corrector


def main(rounds: int = 15) -> None:
    folder = Path(tempfile.mkdtemp(prefix="bench-reload-"))
    write_sets(folder, terms=ALL_TERMS)
    config = load_config(write_config(folder, "bench"))
    build, compile_ = [], []
    for _ in range(rounds):
        t0 = time.perf_counter()
        correctors = [load_axis(config, a.axis, a.coefficients) for a in config.axes]
        t1 = time.perf_counter()
        for c in correctors:
            compile_corrector(c)
        t2 = time.perf_counter()
        build.append(t1 - t0)
        compile_.append(t2 - t1)
    print(f"YAML parser: {yaml_text.BASE_LOADER.__name__}")
    print(f"load + validate 3 sets: {statistics.median(build) * 1e3:.1f} ms (median of {rounds})")
    print(f"generate 3 correctors:  {statistics.median(compile_) * 1e3:.1f} ms")


if __name__ == "__main__":
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="small sizes: checks the script runs")
    main(1 if parser.parse_args().quick else 15)
