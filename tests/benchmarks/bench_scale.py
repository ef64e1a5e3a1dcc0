"""Benchmark: calibrate, apply and noise on sessions of millions of rows, beside numpy.loadtxt.

Generates a session CSV of ``--rows`` rows at 1 kHz (the simulator's sweeps up and down the
paper's 41 rates, 30 s plateaus; written one sweep at a time, so generating is bounded too; several
sizes one after the other, each file deleted before the next is written), the same session with two
auxiliary channels (``temp_c`` cycling through the chamber's swings, with the sensor's bias
following it at 0.01 deg/s/°C, and ``supply_v`` wandering with no effect: the closed loop's
candidates of both, lags and derivatives included, searched at that size), and a static record of
``--noise-rows`` rows, then runs each step in its own process, so that its peak resident memory
(``ru_maxrss`` of that child) is its own: ``numpy.loadtxt`` of the same file (the I/O floor),
``canical calibrate`` (the default, closed loop), ``canical apply`` of the set to the session,
``loadtxt`` and ``calibrate`` of the session with channels, and
``canical noise`` of the static record through the set, each step ``--runs`` times. Prints a table:
step, median wall seconds, largest peak MB, multiple of the floor (the floor's median too); then
how calibrate read each session (as samples, or as means of k) and the load average before and
after (the machine may be shared). ``--baseline DIR`` runs the canical steps with that tree on
PYTHONPATH too (before/after in one run). Files go to a temporary folder (``--tmp``, default the
system's), deleted at the end.

Run: python tests/benchmarks/bench_scale.py [--rows N [N ...]] [--noise-rows N] [--baseline DIR] [--runs N]
     [--quick]
Prints figures; asserts nothing.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

ROOT = Path(__file__).resolve().parents[2]
sys.path.insert(0, str(ROOT))

from canical.sessions.csv_file import format_session  # noqa: E402
from canical.sessions.session import Session  # noqa: E402
from canical.sim.effects import TemperatureEffect  # noqa: E402
from canical.sim.environment import temperature_cycle  # noqa: E402
from canical.sim.gyro import GyroModel  # noqa: E402
from canical.sim.rate_table import step_profile  # noqa: E402
from canical.sim.sessions import paper_rates  # noqa: E402

FS_HZ = 1000.0
DWELL_S = 30.0
TIME = "/usr/bin/time"  # GNU time: the peak RSS of the process it runs


@dataclass(frozen=True)
class Step:
    """One measured process: what it ran, its wall time and peak resident memory."""

    name: str
    wall_s: float
    peak_mb: float


#: The chamber's swings over a session of hours (the channels session's temp_c).
CHAMBER = temperature_cycle(periods_s=(2300.0, 970.0))


def channels(t: np.ndarray, rng: np.random.Generator) -> dict[str, np.ndarray]:
    """temp_c cycling, supply_v wandering about 12 V (a channel the sensor does not feel)."""
    supply = 12.0 + 0.2 * np.sin(2 * np.pi * t / 900.0) + 0.01 * rng.standard_normal(t.size)
    return {"temp_c": CHAMBER(t, None, rng), "supply_v": supply}


def write_session(path: Path, rows: int, *, static: bool, dwell_s: float = DWELL_S, seed: int = 0,
                  with_channels: bool = False) -> None:
    """``rows`` rows at 1 kHz, one sweep (or one static stretch) generated and written at a time;
    ``with_channels``: temp_c (which the sensor's bias follows) and supply_v beside them."""
    gyro = GyroModel(effects=(TemperatureEffect(),) if with_channels else ())
    rng = np.random.default_rng(seed)
    written, sweep, t0 = 0, 0, 0.0
    with path.open("w") as out:
        while written < rows:
            if static:
                n = min(rows - written, 1_000_000)
                t, w = t0 + np.arange(n) / FS_HZ, np.zeros(n)
            else:
                rates = paper_rates() if sweep % 2 == 0 else paper_rates()[::-1]
                t, w = step_profile(rates, dwell_s=dwell_s, fs_hz=FS_HZ, t0_s=t0)
                t, w = t[: rows - written], w[: rows - written]
            aux = channels(t, rng) if with_channels else {}
            raw = gyro.output(t, w, aux=aux, rng=rng, fs_hz=FS_HZ)
            text = format_session(Session(t, raw, w, aux, {"sensor": "BENCH", "axis": "z"}))
            if written:  # metadata and header once
                text = text.split("\n", 3)[3]
            out.write(text)
            written += len(t)
            t0 = float(t[-1]) + 1.0 / FS_HZ
            sweep += 1


#: Runs of each step; its median wall time and largest peak are printed (``--runs``).
RUNS = 3


def measure(name: str, argv: list[str], pythonpath: str, out: list[str] | None = None) -> Step:
    """:func:`measure_once` :data:`RUNS` times: the median wall time (one slow run, the disk
    writing back the file just generated, must not move it) and the largest peak."""
    runs = [measure_once(name, argv, pythonpath, out if i == 0 else None) for i in range(RUNS)]
    return Step(name, float(np.median([r.wall_s for r in runs])), max(r.peak_mb for r in runs))


def measure_once(name: str, argv: list[str], pythonpath: str, out: list[str] | None = None) -> Step:
    """Run ``argv`` in a child process; its wall time and its own peak RSS (its stdout's lines
    appended to ``out``).

    Through ``/usr/bin/time``: a child forked from this process would count this process's
    memory in its ``ru_maxrss`` (Linux keeps the high-water mark across exec).
    """
    env = {**os.environ, "PYTHONPATH": pythonpath, "OPENBLAS_NUM_THREADS": "1", "MPLBACKEND": "Agg"}
    env.pop("CANICAL_PROGRESS", None)
    with tempfile.NamedTemporaryFile("r", suffix=".rss") as rss:
        t0 = time.perf_counter()
        # cwd away from any tree: ``python -m`` puts the working directory before PYTHONPATH
        proc = subprocess.run([TIME, "-f", "%M", "-o", rss.name, *argv], env=env, capture_output=True,
                              text=True, check=False, cwd=tempfile.gettempdir())
        wall = time.perf_counter() - t0
        if proc.returncode != 0:
            sys.exit(f"{name} failed ({proc.returncode}):\n{proc.stdout[-2000:]}\n{proc.stderr[-4000:]}")
        peak_kb = float(rss.read().split()[-1])
    if out is not None:
        out += proc.stdout.splitlines()
    return Step(name, wall, peak_kb / 1024.0)


def loadtxt_argv(path: Path) -> list[str]:
    """numpy.loadtxt of every column of ``path`` (metadata lines are comments, the header skipped)."""
    code = ("import sys, numpy; numpy.loadtxt(sys.argv[1], delimiter=',', comments='#', "
            "skiprows=int(sys.argv[2]))")
    skip = 0
    with path.open() as f:
        for line in f:
            skip += 1
            if not line.startswith("#"):
                break
    return [sys.executable, "-c", code, str(path), str(skip)]


def canical_steps(tmp: Path, session: Path, static: Path, tag: str) -> list[tuple[str, list[str]]]:
    """calibrate, apply and noise as the command line runs them, outputs in ``tmp`` named by ``tag``.

    apply and noise take this tree's set whichever tree runs them: the baseline's calibration may
    differ (a long session read as means), and apply's output is compared for apply alone.
    """
    cset = tmp / "set-this.yaml"
    py = [sys.executable, "-m", "canical"]
    return [
        ("calibrate", [*py, "calibrate", str(session), "-o", str(tmp / f"set-{tag}.yaml")]),
        ("apply", [*py, "apply", str(cset), str(session), "-o", str(tmp / f"applied-{tag}.csv")]),
        ("noise", [*py, "noise", str(static), "--coefficients", str(cset)]),
    ]


def channels_steps(tmp: Path, rows: int, size: str, trees: list[tuple[str, str]], *,
                   quick: bool) -> tuple[Step, list[Step]]:
    """loadtxt and calibrate of the session with two channels (then deleted): its floor, its steps."""
    session = tmp / "channels.csv"
    t0 = time.perf_counter()
    write_session(session, rows, static=False, dwell_s=2.0 if quick else DWELL_S, with_channels=True)
    print(f"session with temp_c, supply_v {rows:,} rows ({session.stat().st_size / 1e6:.0f} MB), generated "
          f"in {time.perf_counter() - t0:.0f} s")
    floor = measure(f"loadtxt channels{size}", loadtxt_argv(session), str(ROOT))
    measured = []
    for tag, path in trees:
        out: list[str] = []
        argv = [sys.executable, "-m", "canical", "calibrate", str(session), "-o",
                str(tmp / "set-channels.yaml")]
        measured.append(measure(f"calibrate channels{size}{tag}", argv, path, out))
        effects = next((line.split(None, 1)[1] for line in out if line.startswith("effects ")), "?")
        print(f"calibrate channels{size}{tag}: effects {effects}")
    session.unlink()
    return floor, measured


def load() -> str:
    """The load average (1, 5, 15 min), beside figures taken on a machine that may be shared."""
    return " ".join(f"{x:.2f}" for x in os.getloadavg())


def main() -> None:
    global RUNS
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rows", type=int, nargs="+", default=[10_000_000], metavar="N",
                        help="session rows (1 kHz), one session per size given [10,000,000]")
    parser.add_argument("--noise-rows", type=int, default=18_000_000,
                        help="static record rows for noise (1 kHz) [18,000,000]")
    parser.add_argument("--baseline", metavar="DIR", help="another tree to run the canical steps with too")
    parser.add_argument("--tmp", metavar="DIR", help="where the generated files go [system temp]")
    parser.add_argument("--runs", type=int, default=RUNS, help=f"runs of each step, median printed [{RUNS}]")
    parser.add_argument("--quick", action="store_true", help="small sizes, one run: checks the script runs")
    args = parser.parse_args()
    RUNS = 1 if args.quick else max(1, args.runs)
    sizes, noise_rows = ([100_000], 60_000) if args.quick else (args.rows, args.noise_rows)
    trees = [("", str(ROOT))]
    if args.baseline:
        trees.append((" (baseline)", str(Path(args.baseline).resolve())))
    print(f"load average before: {load()}")
    tmp = Path(tempfile.mkdtemp(prefix="bench_scale_", dir=args.tmp))
    rows_label = len(sizes) > 1
    steps: list[tuple[Step, Step]] = []
    floors: list[Step] = []
    read_as: list[str] = []
    same: list[bool] = []
    try:
        for rows in sizes:
            session = tmp / "session.csv"
            t0 = time.perf_counter()
            write_session(session, rows, static=False, dwell_s=2.0 if args.quick else DWELL_S)
            print(f"session {rows:,} rows ({session.stat().st_size / 1e6:.0f} MB), generated in "
                  f"{time.perf_counter() - t0:.0f} s")
            size = f" {rows / 1e6:g}M" if rows_label else ""
            floor = measure(f"loadtxt session{size}", loadtxt_argv(session), str(ROOT))
            floors.append(floor)
            for tag, path in trees:
                for name, argv in canical_steps(tmp, session, session, "base" if tag else "this")[:2]:
                    out: list[str] = []
                    steps.append((measure(name + size + tag, argv, path, out), floor))
                    if name == "calibrate":
                        how = next((line.split(None, 1)[1] for line in out if line.startswith("input ")),
                                   f"{rows:,} rows read as they are")
                        read_as.append(f"calibrate{size}{tag}: {how}")
            if args.baseline:
                applied = [(tmp / f"applied-{t}.csv").read_bytes() for t in ("this", "base")]
                same.append(applied[0] == applied[1])
            for leftover in tmp.glob("*.csv"):
                leftover.unlink()
            floor, measured = channels_steps(tmp, rows, size, trees, quick=args.quick)
            floors.append(floor)
            steps += [(step, floor) for step in measured]
        static = tmp / "static.csv"
        t0 = time.perf_counter()
        write_session(static, noise_rows, static=True, seed=1)
        print(f"static record {noise_rows:,} rows ({static.stat().st_size / 1e6:.0f} MB), generated in "
              f"{time.perf_counter() - t0:.0f} s")
        static_floor = measure("loadtxt static", loadtxt_argv(static), str(ROOT))
        floors.append(static_floor)
        for tag, path in trees:
            name, argv = canical_steps(tmp, static, static, "base" if tag else "this")[2]
            steps.append((measure(name + tag, argv, path), static_floor))
        print(f"\n{'step':26s} {'wall s':>8s} {'peak MB':>8s} {'x floor':>8s}")
        for floor in floors:
            print(f"{floor.name:26s} {floor.wall_s:8.2f} {floor.peak_mb:8.0f} {1.0:8.2f}")
        for step, floor in steps:
            print(f"{step.name:26s} {step.wall_s:8.2f} {step.peak_mb:8.0f} {step.wall_s / floor.wall_s:8.2f}")
        print()
        print("\n".join(read_as))
        if args.baseline:
            print(f"apply output identical to the baseline's: {'yes' if all(same) else 'NO'}")
        print(f"load average after: {load()}")
    finally:
        shutil.rmtree(tmp, ignore_errors=True)


if __name__ == "__main__":
    main()
