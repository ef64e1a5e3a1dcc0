"""A continuous sweep cut into short windows that calibrate as plateaus do.

A table sweeping slowly and steadily (a triangle between ±limit, its rate measured by an encoder
at 100 Hz) never stands still, so plateau finding finds nothing. Yet every short stretch of it is
as good as a plateau: over a window of ``W`` seconds the rate moves by ``a·W`` (``a`` the sweep
rate, deg/s²), and the sensor's mean output over the window is its response at the window's mean
rate, up to its curvature: for a response ``f``, the mean of ``f`` over rates spread uniformly by
``a·W`` differs from ``f`` at the mean rate by ``f''·(a·W)²/24``. So the session is cut into
consecutive windows, each a :class:`~canical.calibrate.plateaus.Plateaus` entry, and everything
downstream (fit points, rails, model selection, cross-validation by rate groups, the closed loop,
the reports) runs unchanged, but for the segment points: evenly spaced on a sweep, whose noisy
windows hide the residual extrema steps place them at
(:data:`~canical.calibrate.model_selection.SWEEP_SEGMENT_CHOICES`).

**The window's length.** Its rate spread ``a·W`` is kept within ``MAX_SPREAD_DPS`` (0.5 deg/s):
the sharpest bend a MEMS scale factor shows is the knee of its positive/negative asymmetry, a
few deg/s wide (up to 5 % over 3-10 deg/s in the simulated sensors: ``f''`` up to about 0.03 per
deg/s in rate terms); over 0.5 deg/s its curvature moves a window's mean by about 0.0003 deg/s at most,
a tenth of the held-out error of a good step calibration. Each window holds at least
``WINDOW_UPDATES`` reference updates, so the reference's noise and quantisation average over as
many values as plateau finding's steadiness window uses. Why not longer: the windows' noise is
the same in total whatever their length, but model selection judges sizes by held-out error
against its standard error, and a longer window trades noise for curvature bias at the knee and
a ripple; on the development seeds of ``bench_sweep.py`` wider spreads met the bar less often.

**Time.** The sensor's output lags the table by its filter (a 40 Hz bandwidth is 4 ms), the
reference lags by its transport and its hold; on a sweep a delay ``D`` is a rate error ``a·D``,
of opposite sign on the way up and down. With both directions swept, ``D`` is fitted: the
window rates against a polynomial of the raw output plus ``D`` times each window's sweep rate
(a lag makes the two directions differ, the polynomial cannot). One direction only: ``D`` is minus
the reference's latency estimated from the rate changes (:func:`~canical.calibrate.plateaus.
reference_latency`). A sensor whose output depends on the direction of rotation is, at one sweep
rate, indistinguishable from a delay; a second session swept at another rate would separate them.

**Where the reference cannot support it**, the sweep is refused with the advice to record steps:

* it moves more than ``MAX_SPREAD_DPS / WINDOW_UPDATES`` between two updates (``a·u``, ``u``
  its update interval): a window of enough updates would then spread over more than the bound.
  A quantised reference changes once per step ``q`` of its encoder at the latest, so ``a·u`` is at
  least ``q``: this is also the bound on a coarse encoder;
* its error on a window's mean rate (noise and quantisation, over the independent values in the
  window) exceeds the sensor's own noise on that window's mean: the reference, not the sensor,
  would then set the calibration's error (equal, they make it √2 of the sensor's alone).
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from canical.calibrate.plateaus import Plateaus, reference_latency, span_means
from canical.models.robust_stats import mad_sigma, median_step

MAX_SPREAD_DPS = 0.5  # largest rate spread within one window, deg/s (see the module's docstring)
WINDOW_UPDATES = 10  # fewest reference updates in one window
MIN_WINDOW_ROWS = 20  # fewest sensor rows in one window
MAX_WINDOW_S = 10.0  # a sweep slower than 0.1 deg/s² needs no longer windows than a plateau's
DELAY_ORDER = 7  # the polynomial of the raw output the delay is fitted beside
MIN_DIRECTION_SHARE = 0.2  # each direction's share of windows for the delay to be fitted


@dataclass(frozen=True)
class SweepCheck:
    """Whether the reference supports calibrating from windows, and the figures it was judged by."""

    window_s: float
    moved_per_update_dps: float  # a·u
    reference_error_dps: float  # on a window's mean rate
    sensor_noise_dps: float  # on a window's mean output, as a rate

    def refusal(self) -> str:
        """Why the reference cannot support the sweep ("" when it can), as a clause of one line."""
        if self.moved_per_update_dps > MAX_SPREAD_DPS / WINDOW_UPDATES:
            return (f", its reference too coarse or slow for it: {self.moved_per_update_dps:.2g} deg/s "
                    f"between updates (above {MAX_SPREAD_DPS / WINDOW_UPDATES:.2g})")
        if self.reference_error_dps > self.sensor_noise_dps:
            return (f", its reference too noisy for it: {self.reference_error_dps:.2g} deg/s on a window "
                    f"(the sensor's noise: {self.sensor_noise_dps:.2g})")
        return ""


@dataclass(frozen=True)
class _Windows:
    """Consecutive windows of one sweep direction: row ranges, mean reference and sweep rate."""

    start: np.ndarray
    stop: np.ndarray
    ref_mean: np.ndarray
    slope: np.ndarray  # deg/s² per window


def window_length(sweep_dps2: float, update_s: float, row_s: float) -> float:
    """A window's length: its rate spread within the bound, at least enough updates and rows."""
    spread_s = MAX_SPREAD_DPS / sweep_dps2 if sweep_dps2 > 0 else MAX_WINDOW_S
    return float(min(max(spread_s, WINDOW_UPDATES * update_s, MIN_WINDOW_ROWS * row_s), MAX_WINDOW_S))


def sweep_check(t: np.ndarray, ref: np.ndarray, raw: np.ndarray, found: Plateaus) -> SweepCheck:
    """The figures the refusal is decided on, from what plateau finding saw and the session."""
    row_s = median_step(t, 0.0) or found.update_s
    u = max(found.update_s, row_s)
    a = found.sweep_dps2
    w = window_length(a, u, row_s)
    lsb = _reference_step(ref)
    updates = max(1.0, w / u)
    # Quantisation errors are independent only once the sweep crosses a step between values.
    quantised = max(1.0, min(updates, a * w / lsb)) if lsb > 0 else updates
    ref_err = float(np.sqrt(found.ref_noise_dps**2 / updates + lsb**2 / 12.0 / quantised))
    return SweepCheck(w, a * u, ref_err, _sensor_noise(ref, raw) / np.sqrt(max(1.0, w / row_s)))


def sweep_windows(t: np.ndarray, ref: np.ndarray, raw: np.ndarray, found: Plateaus, check: SweepCheck,
                  latency_s: float | None) -> Plateaus:
    """The sweep as consecutive windows, each with its rate shifted by the fitted delay.

    ``latency_s``: the reference's latency where the user gave it (used when only one direction
    is swept; else estimated).
    """
    win = _cut(t, ref, check.window_s)
    raw_mean = span_means(raw, win.start, win.stop)
    delay = _delay(win, raw_mean)
    if delay is None:
        late = latency_s if latency_s is not None else reference_latency(t, ref, raw, found.update_s)
        delay = -late
    label = np.full(t.size, -1, dtype=np.int64)
    for i, (a, b) in enumerate(zip(win.start, win.stop, strict=True)):
        label[a:b] = i
    n_used = int(np.sum(win.stop - win.start))
    sems = np.full(win.start.size, check.reference_error_dps)
    return replace(found, label=label, rate_dps=win.ref_mean - delay * win.slope, start=win.start,
                   stop=win.stop, n_transition=t.size - n_used, n_settling=0, rate_sem_dps=sems,
                   latency_s=float(-delay), sweep_window_s=check.window_s)


def _cut(t: np.ndarray, ref: np.ndarray, window_s: float) -> _Windows:
    """Consecutive windows from the session's start; those where the sweep turns are dropped
    (their two halves sweep in opposite directions: no single rate and delay describe them)."""
    edges = np.searchsorted(t, np.arange(t[0], t[-1], window_s))
    start, stop = edges[:-1], edges[1:]
    keep = stop - start >= MIN_WINDOW_ROWS
    start, stop = start[keep], stop[keep]
    mid = (start + stop) // 2
    slope = _slopes(t, ref, start, stop)
    first, second = _slopes(t, ref, start, mid), _slopes(t, ref, mid, stop)
    steady = (np.sign(first) == np.sign(slope)) & (np.sign(second) == np.sign(slope)) & (slope != 0)
    start, stop = start[steady], stop[steady]
    return _Windows(start, stop, span_means(ref, start, stop), slope[steady])


def _slopes(t: np.ndarray, y: np.ndarray, start: np.ndarray, stop: np.ndarray) -> np.ndarray:
    """Least-squares slope of y against t over each ``[start, stop)``, from cumulative sums."""
    tc = t - t[0]
    n = (stop - start).astype(float)
    st, sy = span_means(tc, start, stop), span_means(y, start, stop)
    stt, sty = span_means(tc * tc, start, stop), span_means(tc * y, start, stop)
    var = stt - st * st
    slope: np.ndarray = np.where((var > 0) & (n > 1), (sty - st * sy) / np.where(var > 0, var, 1.0), 0.0)
    return slope


def _delay(win: _Windows, raw_mean: np.ndarray) -> float | None:
    """The sensor's delay behind the reference, s, fitted where both directions are swept (None
    where one direction dominates: a delay is then a bias)."""
    up = float(np.mean(win.slope > 0)) if win.slope.size else 0.0
    if win.slope.size < 2 * DELAY_ORDER or min(up, 1.0 - up) < MIN_DIRECTION_SHARE:
        return None
    u = (raw_mean - raw_mean.mean()) / (np.ptp(raw_mean) or 1.0)
    columns = np.vander(u, DELAY_ORDER + 1)
    design = np.column_stack((columns, win.slope))
    coef = np.linalg.lstsq(design, win.ref_mean, rcond=None)[0]
    return float(coef[-1])


def _reference_step(ref: np.ndarray) -> float:
    """The reference's quantisation step: the smallest change it makes (0 for a smooth one,
    whose changes are not on a grid)."""
    d = np.abs(np.diff(ref))
    d = d[d > 0]
    if d.size < 10:
        return 0.0
    step = float(np.quantile(d, 0.05))
    on_grid = np.abs(d / step - np.round(d / step)) < 0.01
    return step if np.mean(on_grid) > 0.9 else 0.0


def _sensor_noise(ref: np.ndarray, raw: np.ndarray) -> float:
    """The sensor's noise per sample, deg/s: second differences (a sweep's slope cancels) over the
    output's slope against the reference."""
    d2 = raw[2:] - 2 * raw[1:-1] + raw[:-2]
    sigma_raw = mad_sigma(d2) / np.sqrt(6.0)
    if sigma_raw == 0.0:
        sigma_raw = float(np.std(d2)) / np.sqrt(6.0)
    slope = abs(float(np.polyfit(ref, raw, 1)[0])) if np.ptp(ref) > 0 else 0.0
    return float(sigma_raw / slope) if slope > 0 else float("inf")
