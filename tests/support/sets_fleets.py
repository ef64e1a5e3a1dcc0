"""bench_fleet's sets part on chosen groups of fleets: the explored ones and those drawn from seeds
from 1000 and from 2001 (:data:`support.replay_fleets.DRAWN`, :data:`~support.replay_fleets.FRESH`),
never the blind ones.

Run: python tests/support/sets_fleets.py [--groups explored,drawn,fresh] [--keep DIR [--replay-again]]

Why apart from ``bench_fleet.py``: its figures are recorded with a digest of its source, so the
lead re-records them all, blind fleets included; this prints the same table (its rows from
``bench_fleet``) for the fleets a change may be developed on. ``--keep`` leaves the fleets built
in DIR (the cleanup of thirty fleets' datasets takes minutes); ``--replay-again`` replays those
again, the fleets and their proposals unchanged (before and after a change to the replay).
"""

from __future__ import annotations

import argparse
import os
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
from bench_fleet import EXPLORED, SETS_HEADER, _sets_row

from support import replay_fleets

GROUPS = {"explored": EXPLORED, "drawn": replay_fleets.DRAWN, "fresh": replay_fleets.FRESH}


def run(root: Path, groups: list[str], again: bool = False) -> None:
    results: dict[str, list[replay_fleets.FleetRatio]] = {}
    for name in groups:
        results[name] = []
        for spec in GROUPS[name]:
            folder = root / f"sets-{spec.seed}-{spec.vehicles}-{spec.drives}"
            if not (folder / "replay.csv").is_file():
                replay_fleets.build(folder, spec)
            elif again:
                replay_fleets.replay(folder)
            result = replay_fleets.judge(folder, spec)
            results[name].append(result)
            print(_sets_row(f"{name}: {spec.seed}, {spec.vehicles}, {spec.drives}", result.wrong,
                            result.others, result.unchanged_same), flush=True)
    for name, got in results.items():
        print(_sets_row(f"**all {name} ({len(got)} fleets)**", replay_fleets.combined([r.wrong for r in got]),
                        replay_fleets.combined([r.others for r in got]), all(r.unchanged_same for r in got)))


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--groups", default="explored,drawn", help=f"of {','.join(GROUPS)}")
    p.add_argument("--keep", type=Path, help="build the fleets here and leave them")
    p.add_argument("--replay-again", action="store_true",
                   help="with --keep: replay the fleets built there again (after a change to the replay)")
    args = p.parse_args()
    groups = args.groups.split(",")
    if set(groups) - set(GROUPS):
        p.error(f"--groups: some of {','.join(GROUPS)}")
    os.environ.setdefault("OPENBLAS_NUM_THREADS", "1")
    print(SETS_HEADER)
    if args.keep:
        run(args.keep, groups, args.replay_again)
        return
    with tempfile.TemporaryDirectory(prefix="sets-fleets-") as tmp:
        run(Path(tmp), groups)


if __name__ == "__main__":
    main()
