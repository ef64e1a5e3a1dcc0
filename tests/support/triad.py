"""A simulated triad's sessions written as CSV files, for the three-axis tests."""

from pathlib import Path

from canical.sessions.triad_session import format_triad_session
from canical.sim.triad import axis_session, multi_axis_rates, multi_axis_session, random_triad

#: Short sessions: the plateaus of the full protocol, 1.5 s each (what the tests need, quickly).
DWELL_S = 1.5
#: The multi-axis session's plateaus: long enough on every axis (the validation's own).
MULTI_DWELL_S = 3.0


def write_triad_sessions(directory: Path, seed: int = 0, axes=("x", "-y", "z"), multi: bool = True,
                         sensor: str = "SIM-TRIAD") -> list[Path]:
    """One CSV per table axis (named x.csv, neg_y.csv...) and a multi-axis one; their paths."""
    triad = random_triad(seed)
    paths = []
    for k, axis in enumerate(axes):
        path = directory / f"{axis.replace('-', 'neg_')}.csv"
        session = axis_session(triad, axis, dwell_s=DWELL_S, seed=100 * seed + k, sensor=sensor)
        path.write_text(format_triad_session(session))
        paths.append(path)
    if multi:
        path = directory / "multi.csv"
        session = multi_axis_session(triad, multi_axis_rates(8, seed=seed), dwell_s=MULTI_DWELL_S,
                                     seed=100 * seed + 9, sensor=sensor)
        path.write_text(format_triad_session(session))
        paths.append(path)
    return paths
