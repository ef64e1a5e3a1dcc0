"""Abrupt steps of a sensor's bias within a session, found in what the smooth explanations leave.

A bias that jumps (a shock, a mode change) is a drift of the session no smooth form of time fits:
the spline the drift competitor is leaves a kink at each jump, and a channel that happens to wander
at the time can take it, so the channel is blamed for the drift (a distractor written into the set)
or a real effect's form loses to the misfit around the jumps. The loop finds the jumps in the
plateau means of the residual the smooth drift leaves (:func:`change_times`) and judges the
channel against the drift with the jumps in both (:func:`step_terms`): a property of this session,
never written into the set.
"""

from __future__ import annotations

import numpy as np

from canical.sets.term_kinds import CHANNEL_SPLINE
from canical.sets.terms import Term

#: The most jumps looked for: more than a few jumps in one session is a channel's doing (a level
#: effect of a channel that changes in steps jumps at every change), not a shocked sensor's.
MAX_STEPS = 3
#: A jump is taken when the lines either side of it differ there by this many standard errors.
STEP_T = 5.0
#: A channel jumping at the same boundary, by this many of its own standard errors and this share
#: of its range over the session, takes the jump (its step is the channel's effect to explain).
CHANNEL_JUMP_T = 4.0
CHANNEL_JUMP_SHARE = 0.2
#: Plateaus either side of a boundary that its two lines are fitted to.
WINDOW = 4


def change_times(time_s: np.ndarray, residual: np.ndarray,
                 channels: tuple[np.ndarray, ...] = ()) -> tuple[float, ...]:
    """The times of the bias's jumps in ``residual`` (one value per plateau at ``time_s``): at each
    boundary between plateaus, the line through the :data:`WINDOW` plateaus before it and the line
    through those after, extrapolated to it, differ by :data:`STEP_T` standard errors or more (a
    smooth drift or effect bends there, it does not jump), and no channel (``channels``, per
    plateau) jumps at the same boundary (that jump is the channel's to explain). The largest
    first, each taken out before the next is looked for, up to :data:`MAX_STEPS`."""
    order = np.argsort(time_s, kind="stable")
    t, y = np.asarray(time_s, dtype=float)[order], np.asarray(residual, dtype=float).copy()[order]
    if y.size < 2 * WINDOW + 1:
        return ()
    vetoed = np.zeros(y.size + 1, dtype=bool)
    for values in channels:
        vetoed |= _channel_jumps(t, np.asarray(values, dtype=float)[order])
    cuts: list[int] = []
    while len(cuts) < MAX_STEPS:
        z = _jumps(t, y)
        z[vetoed] = 0.0
        k = int(np.argmax(np.abs(z)))
        if abs(z[k]) < STEP_T:
            break
        y[k:] -= _jump_size(t, y, k)
        cuts.append(k)
    return tuple(float(0.5 * (t[k - 1] + t[k])) for k in sorted(cuts))


def step_terms(times: tuple[float, ...], start_s: float, end_s: float, clock: str) -> tuple[Term, ...]:
    """One bias term per jump: a function of ``clock`` that is 0 before the jump and 1 after."""
    return tuple(Term.of(CHANNEL_SPLINE, "bias", 0.0, channel=clock, knots=(start_s, at, end_s),
                         pieces=((0.0, 0.0, 0.0, 0.0), (1.0, 0.0, 0.0, 0.0)))
                 for at in times if start_s < at < end_s)


def merge_times(known: tuple[float, ...], found: tuple[float, ...], within_s: float) -> tuple[float, ...]:
    """``known`` and the times of ``found`` that are new, in order: one within ``within_s`` (a
    plateau's spacing) of a known one is that jump again, which another comparison's residual put
    at the neighbouring boundary."""
    times = list(known)
    for t in found:
        if all(abs(t - k) > within_s for k in times):
            times.append(t)
    return tuple(sorted(times))


def _channel_jumps(t: np.ndarray, v: np.ndarray) -> np.ndarray:
    """Per boundary: whether the channel jumps there, by :data:`CHANNEL_JUMP_T` of its standard
    errors and :data:`CHANNEL_JUMP_SHARE` of its range (a quiet channel's bend at a ramp's turn is
    many of its tiny standard errors, yet no jump)."""
    sizes, z = _jump_table(t, v)
    span = float(np.ptp(v)) if v.size else 0.0
    return (np.abs(z) >= CHANNEL_JUMP_T) & (np.abs(sizes) >= CHANNEL_JUMP_SHARE * span)


def _jumps(t: np.ndarray, y: np.ndarray) -> np.ndarray:
    """Per boundary: the jump there in standard errors (:func:`_jump_table`)."""
    return _jump_table(t, y)[1]


def _jump_table(t: np.ndarray, y: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Per boundary k (between values k-1 and k; 0 and n have none): the jump there, and that jump
    in standard errors, the noise read from second differences (robust to a trend and to a jump);
    zeros where the noise is nil."""
    sigma = float(1.4826 * np.median(np.abs(np.diff(y, 2))) / np.sqrt(6.0)) if y.size > 2 else 0.0
    sizes, z = np.zeros(y.size + 1), np.zeros(y.size + 1)
    if not sigma > 0:
        return sizes, z
    for k in range(WINDOW, y.size - WINDOW + 1):
        sizes[k], factor = _jump_fit(t, y, k)
        z[k] = sizes[k] / (sigma * np.sqrt(factor))
    return sizes, z


def _jump_size(t: np.ndarray, y: np.ndarray, k: int) -> float:
    return _jump_fit(t, y, k)[0]


def _jump_fit(t: np.ndarray, y: np.ndarray, k: int) -> tuple[float, float]:
    """The jump at boundary k between the two sides' lines, and its variance in units of one value's."""
    at = 0.5 * (t[k - 1] + t[k])
    left, v_left = _line_at(t[k - WINDOW:k], y[k - WINDOW:k], at)
    right, v_right = _line_at(t[k:k + WINDOW], y[k:k + WINDOW], at)
    return right - left, v_left + v_right


def _line_at(t: np.ndarray, y: np.ndarray, at: float) -> tuple[float, float]:
    """A least-squares line's value at ``at`` and its variance factor (1/n + (at - t̄)²/Sxx)."""
    tc = t - t.mean()
    sxx = float(tc @ tc)
    slope = float(tc @ (y - y.mean())) / sxx
    return float(y.mean() + slope * (at - t.mean())), 1.0 / t.size + (at - t.mean()) ** 2 / sxx
