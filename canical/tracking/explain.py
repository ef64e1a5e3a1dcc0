"""What the learned bias follows: temperature, time since power-on, or neither, from the windows used.

Why: the tracker carries the bias between stops with a temperature slope; a drive's windows say
whether that was the right effect. Each window the tracker learned from measured the bias at one
temperature and one time since power-on; least squares with an offset per power-on, plus a
temperature term, a time term or both, tells which explains the measured bias and by how much
(the rms left over, before and after the term). Runs once per drive, offline.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from canical.tracking.events import TakenWindow

OFFSETS = "an offset per power-on"
#: The least evidence a conclusion is drawn from: this many windows, their times since power-on
#: spanning this long. Why: a term fitted to 3 windows over 4 s (5 numbers from 3) fits noise,
#: and a drift with time or temperature shows only over minutes.
MIN_WINDOWS = 10
MIN_SPAN_S = 60.0


@dataclass(frozen=True)
class Explanation:
    """One model of the measured bias and how well it fits the windows."""

    model: str
    rms_dps: float  # left over
    terms: dict[str, float]  # slope per °C and per s, where the model has them


def too_little_evidence(taken: tuple[TakenWindow, ...] | list[TakenWindow]) -> str | None:
    """Why the windows cannot tell what the bias follows (None: they can)."""
    times = [0.5 * (w.start_s + w.end_s) for w in taken]
    span = max(times) - min(times) if times else 0.0
    if len(taken) >= MIN_WINDOWS and span >= MIN_SPAN_S:
        return None
    return (f"{len(taken)} window(s) over {span:.0f} s since power-on; at least {MIN_WINDOWS} over "
            f"{MIN_SPAN_S:.0f} s are needed")


def explain(taken: tuple[TakenWindow, ...] | list[TakenWindow], axis: int = 0) -> list[Explanation]:
    """Offsets alone, + temperature, + time since power-on, + both; best (least rms) first; none
    from too little evidence (:func:`too_little_evidence`)."""
    if too_little_evidence(taken) is not None:
        return []
    cycles = sorted({w.power_cycle for w in taken})
    offsets = np.array([[w.power_cycle == c for c in cycles] for w in taken], dtype=float)
    temp = np.array([w.temp_c for w in taken])
    time_s = np.array([0.5 * (w.start_s + w.end_s) for w in taken])
    measured = np.array([w.mean_dps[axis] for w in taken])
    columns = {"temperature (deg/s/°C)": temp - temp.mean(), "time since power-on (deg/s/s)": time_s}
    models = {OFFSETS: [], "+ temperature": ["temperature (deg/s/°C)"],
              "+ time since power-on": ["time since power-on (deg/s/s)"],
              "+ temperature and time": list(columns)}
    out = []
    for name, keys in models.items():
        design = np.column_stack([offsets, *[columns[k] for k in keys]])
        if np.linalg.matrix_rank(design) < design.shape[1] or design.shape[0] <= design.shape[1]:
            continue
        coef, *_ = np.linalg.lstsq(design, measured, rcond=None)
        rms = float(np.sqrt(np.mean((measured - design @ coef) ** 2)))
        out.append(Explanation(name if name == OFFSETS else f"{OFFSETS} {name}", rms,
                               {k: float(c) for k, c in zip(keys, coef[len(cycles):], strict=True)}))
    return sorted(out, key=lambda e: e.rms_dps)


def chosen(models: list[Explanation], margin: float = 1.1) -> Explanation:
    """The simplest model whose rms is within ``margin`` of the best: a term must earn its place."""
    best = min(m.rms_dps for m in models)
    return min((m for m in models if m.rms_dps <= margin * best), key=lambda m: (len(m.terms), m.rms_dps))
