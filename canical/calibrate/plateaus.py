"""Find the constant-rate plateaus of a turntable session, as real tables record them.

Only samples taken at a steady, settled table rate say anything about the scale factor.
Real recordings make "steady" hard to see sample by sample: a gentle ramp (1 deg/s²) changes
the reference by less than its own jitter between two samples, an encoder-derived reference
is noisy, a reference updated at 10 Hz is held between updates, and rows go missing. So:

* **Steadiness is judged over a time window**, robustly: at every instant the median of the
  reference over the window before is compared with the median over the window after
  (on a uniform time grid, holding the latest value, so lost rows, duplicated timestamps and
  uneven sampling change nothing). A ramp of ``a`` deg/s² moves that difference by ``a·W``;
  a single outlier does not move a median at all.
* **The tolerance follows from the session**: the reference's own noise is estimated from
  its successive updates (median absolute deviation) and the tolerance is set to a multiple
  of the noise of a window median, never below a floor. Both are reported.
* **A noiseless reference** (the commanded rate, exact on every plateau) shows the row where
  each plateau begins: the steady stretches start there.
* **Both ends of each plateau are guarded.** The start: the servo's overshoot and ringing
  and the sensor's filter settle over ``settle_s``. Auto, it is the settling the session
  shows: after each rate change, how long until the sensor's own output, averaged over a
  short window, stays within its noise of the plateau's final level, pooled over the
  plateaus (upper quartile: a few odd plateaus do not set it, most are covered); never
  below a floor (a few rows, or half the steadiness window where the reference's noise
  blurs where a stretch begins). A commanded reference cannot show the table ringing; the
  sensor does. Without the sensor's output: 0.5 s or a tenth of the stretch. The end: a
  reference that is held between updates or late shows the next ramp only after its
  update interval (estimated from the spacing of its changes, i.e. how long values are
  held) plus its latency (given, or estimated from when the sensor and the reference each
  show the rate changing); that much is cut.
* **A settled flag** recorded by the table narrows the plateaus further; it never makes a
  visibly moving reference steady.

Each steady stretch is its own plateau, so a session with repeated sweeps gives several
plateaus at the same rate; cross-validation groups and hysteresis both rely on that.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass

import numpy as np

from canical.errors import CanicalError
from canical.models.robust_stats import mad_sigma, median_step

MIN_WINDOW_S = 0.5  # shortest window over which steadiness is judged
WINDOW_UPDATES = 8  # ...and at least this many reference updates
TOL_FLOOR_DPS = 0.01  # tolerance floor, for references without noise
TOL_SIGMAS = 6.0  # tolerance in standard deviations of a window median's difference
DEFAULT_SETTLE_S = 0.5  # start guard without the sensor's output to observe settling in
SETTLE_FRACTION = 0.1
SETTLE_FLOOR_S = 0.1  # start guard never below this (nor below half a window for a noisy reference)
SETTLE_WINDOW_S = 0.1  # the sensor's level is averaged over this (or MIN_SETTLE_ROWS rows)...
MIN_SETTLE_ROWS = 5
SETTLE_SIGMAS = 4.0  # ...and is settled within this many standard errors of the final level
SETTLE_QUANTILE = 0.75  # pooled over plateaus
MAX_UPDATE_S = 1.0
GRID_PER_WINDOW = 10  # steadiness is judged every tenth of a window
MIN_WINDOW_ROWS = 5
MAX_LATENCY_S = 1.0  # latencies looked for when estimating one


@dataclass(frozen=True)
class Plateaus:
    """Per-sample plateau labels, per-plateau summaries, and what the session showed."""

    label: np.ndarray  # int per sample: plateau index, or -1 when left out
    rate_dps: np.ndarray  # per plateau: reference rate (robust mean)
    start: np.ndarray  # per plateau: first used sample index
    stop: np.ndarray  # per plateau: one past the last used sample index
    n_transition: int  # samples at a changing table rate
    n_settling: int  # samples dropped at the guarded ends of plateaus
    ref_noise_dps: float = 0.0  # estimated noise of one reference update
    rate_tol_dps: float = 0.0  # tolerance used on the window medians' difference
    update_s: float = 0.0  # the reference's update interval (how long values are held)
    window_s: float = 0.0
    settle_s: float = 0.0  # start guard (minimum; a tenth of long stretches without a sensor output)
    settle_source: str = "default"  # "given", "observed" (from the sensor's output) or "default"
    observed_settling_s: float | None = None  # settling seen in the sensor's output, pooled
    end_guard_s: float = 0.0  # end guard: update interval plus latency
    latency_s: float = 0.0  # the reference's latency behind the sensor (given or estimated)
    rate_changes: int = 0  # moving stretches seen
    longest_steady_s: float = 0.0  # longest steady stretch, before guards
    n_not_settled: int = 0  # steady samples the table flagged as not settled
    rate_sem_dps: np.ndarray | None = None  # per plateau: standard error of its rate
    n_short: int = 0  # steady stretches left out as shorter than the minimum
    sweep_dps2: float = 0.0  # median net change of the reference per second, window to window
    #: > 0: these are a continuous sweep's consecutive windows of this length, not steady stretches
    #: (:mod:`canical.calibrate.sweep_windows`); no window stands at zero rate.
    sweep_window_s: float = 0.0

    def rate_uncertainty(self) -> np.ndarray:
        """Per plateau: the standard error of its reference rate (0 for a noiseless reference)."""
        return self.rate_sem_dps if self.rate_sem_dps is not None else np.zeros(self.count)

    @property
    def sweeping(self) -> bool:
        """The reference never stands still: its net change over a window is many times its noise
        (and the tolerance) and no stretch is a window long. A continuous sweep, not a noisy
        reference."""
        moved = self.sweep_dps2 * self.window_s > max(SWEEP_NOISES * self.ref_noise_dps, self.rate_tol_dps)
        return self.longest_steady_s < self.window_s and moved

    @property
    def count(self) -> int:
        return int(self.rate_dps.shape[0])

    @property
    def n_used(self) -> int:
        return int(np.sum(self.stop - self.start))

    def describe(self) -> PlateauFinding:
        """What plateau finding saw and set, for the report."""
        return PlateauFinding(
            reference_noise_dps=self.ref_noise_dps,
            rate_tol_dps=self.rate_tol_dps,
            reference_update_s=self.update_s,
            window_s=self.window_s,
            settle_s=self.settle_s,
            settle_source=self.settle_source,
            observed_settling_s=self.observed_settling_s,
            end_guard_s=self.end_guard_s,
            reference_latency_s=self.latency_s,
            rate_changes=self.rate_changes,
            longest_steady_s=self.longest_steady_s,
            not_settled_samples=self.n_not_settled,
            short_stretches=self.n_short,
            sweep_window_s=self.sweep_window_s or None,
        )


@dataclass(frozen=True)
class PlateauFinding:
    """What plateau finding saw and set, as the report and the command's summary read it; the
    fields are the report's keys, in its order (:meth:`to_dict`), so report.json stays as it was."""

    reference_noise_dps: float
    rate_tol_dps: float
    reference_update_s: float
    window_s: float
    settle_s: float
    settle_source: str  # "given", "observed" or "default"
    observed_settling_s: float | None
    end_guard_s: float
    reference_latency_s: float
    rate_changes: int
    longest_steady_s: float
    not_settled_samples: int
    short_stretches: int
    sweep_window_s: float | None = None  # a continuous sweep's windows (None: plateaus, and no key)

    def to_dict(self) -> dict[str, float | int | str | None]:
        out = asdict(self)
        if self.sweep_window_s is None:
            del out["sweep_window_s"]
        return out


def check_time_order(time_s: np.ndarray, what: str = "time_s") -> None:
    """Refuse a session whose time goes backwards, naming the first bad row (1-based)."""
    t = np.asarray(time_s, dtype=float)
    back = np.flatnonzero(np.diff(t) < 0)
    if back.size:
        i = int(back[0]) + 1
        raise CanicalError(
            f"{what} goes backwards at row {i + 1} ({t[i]:.6g} s after {t[i - 1]:.6g} s): "
            "sort the rows or fix the clock"
        )


def reference_update_s(time_s: np.ndarray, ref_dps: np.ndarray, row_step: float | None = None) -> float:
    """How long the reference holds a value: the typical spacing of its changes while it moves.

    A reference sent at 10 Hz and joined to 100 Hz sensor rows repeats each value ten times;
    its changes are then 0.1 s apart on ramps (and wherever it has noise). Spacings longer
    than a second are plateaus of a noiseless reference, not holding. ``row_step``: the rows'
    :func:`~canical.models.robust_stats.median_step` (0.0 when time never advances) where the caller has
    it (a long session's takes a while to make).
    """
    t = np.asarray(time_s, dtype=float)
    sample_s = (row_step or 1.0) if row_step is not None else median_step(t, 1.0)
    changes = np.flatnonzero(np.diff(ref_dps) != 0) + 1
    gaps = np.diff(t[changes])
    gaps = gaps[(gaps > 0) & (gaps < MAX_UPDATE_S)]
    return max(sample_s, float(np.median(gaps))) if gaps.size >= 3 else sample_s


def reference_noise(time_s: np.ndarray, ref_dps: np.ndarray, update_s: float) -> float:
    """Noise of one reference update, deg/s rms, from the reference sampled once per update.

    Second differences cancel ramps (and nearly cancel S-curves); their median absolute
    deviation ignores steps. A noiseless reference (commanded rate) gives 0, a held one is
    not mistaken for a quiet one because it is sampled at its own update interval.
    """
    t = np.asarray(time_s, dtype=float)
    ref = np.asarray(ref_dps, dtype=float)
    grid_t = np.arange(t[0], t[-1], update_s)
    if grid_t.size < 4:
        return 0.0
    x = ref[np.clip(np.searchsorted(t, grid_t, side="right") - 1, 0, ref.size - 1)]
    d2 = x[2:] - 2 * x[1:-1] + x[:-2]
    return float(mad_sigma(d2) / np.sqrt(6.0))


def reference_latency(time_s: np.ndarray, ref_dps: np.ndarray, raw: np.ndarray, update_s: float,
                      max_lag_s: float = MAX_LATENCY_S, row_step: float | None = None) -> float:
    """How late the reference is behind the sensor, s, from when each shows the rate changing.

    Cross-correlates the reference's and the sensor's changes (each smoothed over one
    reference update, so a held reference lines up with a smooth sensor) over lags up to
    ``max_lag_s``. A held reference is late by half an update on average; that part is the
    hold guard's, so it is taken off. Never negative: an early reference needs no end guard.
    ``row_step``: the rows' median step where the caller has it, as for :func:`reference_update_s`.
    """
    t = np.asarray(time_s, dtype=float)
    step = median_step(t, 0.0) if row_step is None else row_step
    if t.size < 16 or step == 0.0:
        return 0.0
    grid = np.arange(t[0], t[-1], step)
    idx = np.clip(np.searchsorted(t, grid, side="right") - 1, 0, t.size - 1)
    x = np.diff(np.asarray(ref_dps, dtype=float)[idx])
    y = np.diff(np.asarray(raw, dtype=float)[idx])
    k = max(1, round(update_s / step))
    kernel = np.ones(k) / k
    x, y = np.convolve(x, kernel, mode="same"), np.convolve(y, kernel, mode="same")
    if not (np.any(x) and np.any(y)):
        return 0.0
    reach = min(round(max_lag_s / step), x.size - 1)
    c = near_correlation(x, y, reach)
    lag = float(np.argmax(np.abs(c)) - reach) * step  # the sensor may count either way
    held = update_s if update_s > 1.5 * step else 0.0
    return max(0.0, lag - held / 2)


def near_correlation(x: np.ndarray, y: np.ndarray, reach: int, block: int | None = None) -> np.ndarray:
    """``correlate(x, y)`` (full, same lengths) at the lags −reach…reach only, a block of x at a time.

    Why: the full correlation of a session of millions of samples takes a transform twice its
    length and gigabytes; the lags wanted are a second's worth. Each block of x meets only the
    part of y within ``reach`` of it, and the blocks' correlations add up to the whole's (equal
    within rounding). The default block makes each transform 2¹⁷ long, a power of two.
    """
    n = x.size
    block = max(1, (1 << 16) - reach) if block is None else block
    out = np.zeros(2 * reach + 1)
    for start in range(0, n, block):
        stop = min(start + block, n)
        lo, hi = max(0, start - reach), min(n, stop + reach)
        c = full_correlation(x[start:stop], y[lo:hi])
        lags = np.arange(-(hi - lo - 1), stop - start) + (start - lo)
        near = np.abs(lags) <= reach
        out[lags[near] + reach] += c[near]
    return out


def full_correlation(x: np.ndarray, y: np.ndarray) -> np.ndarray:
    """``scipy.signal.correlate(x, y, mode="full")`` through numpy's FFT: Σₙ x[n + l]·y[n] at the
    lags l = −(len(y) − 1)…len(x) − 1.

    Why not scipy's: importing scipy.signal takes half a second (it pulls in scipy.stats), a tenth
    of calibrating ten million samples, for one transform pair.
    """
    m, p = x.size, y.size
    size = 1 << (m + p - 2).bit_length()  # a power of two ≥ m + p − 1: no wrap-around
    r = np.fft.irfft(np.fft.rfft(x, size) * np.conj(np.fft.rfft(y, size)), size)
    out: np.ndarray = np.concatenate((r[size - (p - 1):], r[:m]))
    return out


def detect_plateaus(
    time_s: np.ndarray,
    ref_dps: np.ndarray,
    *,
    rate_tol: float | None = None,
    min_duration_s: float = 1.0,
    settle_s: float | None = None,
    settled: np.ndarray | None = None,
    latency_s: float | None = 0.0,
    window_s: float | None = None,
    raw: np.ndarray | None = None,
) -> Plateaus:
    """Label the settled constant-rate samples of a session (``None`` options: from the session).

    ``latency_s=None`` estimates the reference's latency from the sensor's ``raw`` output.
    """
    ref = np.asarray(ref_dps, dtype=float)
    t = np.asarray(time_s, dtype=float)
    n = ref.shape[0]
    label = np.full(n, -1, dtype=np.int64)
    if n < 2:
        empty = np.zeros(0)
        return Plateaus(label, empty, empty.astype(int), empty.astype(int), n, 0)
    check_time_order(t)
    row_step = median_step(t, 0.0)  # the rows' step, once: each use below would make it again
    update = reference_update_s(t, ref, row_step=row_step)
    noise = reference_noise(t, ref, update)
    window = window_s if window_s is not None else max(MIN_WINDOW_S, WINDOW_UPDATES * update)
    row_s = row_step or update
    stretches, tol, rate_changes = _steady_stretches(t, ref, window, noise, update, row_s, rate_tol,
                                                     row_step)
    # What the reference itself shows, for the report and the errors (before the flag).
    longest = max((float(t[b - 1] - t[a]) for a, b in stretches), default=0.0)
    n_flagged = 0
    if settled is not None:
        stretches, n_flagged = _narrowed_by_flag(stretches, np.asarray(settled, dtype=bool))
    if latency_s is None:
        latency_s = reference_latency(t, ref, raw, update, row_step=row_step) if raw is not None else 0.0
    # A value held between updates may be up to one update old; one sent with every row is current.
    end_guard = (update if update > 1.5 * row_s else 0.0) + max(latency_s, 0.0)
    observed = None
    if raw is not None:
        observed = observed_settling_s(t, np.asarray(raw, dtype=float), stretches, min_duration_s, row_s,
                                       end_guard)
    settle_s, source = _start_guard(settle_s, observed, noise, window)
    guards = _Guards(settle_s, end_guard, slack=0.25 * row_s)
    cut = _cut_plateaus(t, ref, stretches, guards, min_duration_s=min_duration_s, window=window, tol=tol)
    for i, (first, last) in enumerate(zip(cut.starts, cut.stops, strict=True)):
        label[first:last] = i
    # Held repeats are one update: the rate averages (duration / update interval) of them.
    sems = [noise / np.sqrt(max(1.0, (t[last - 1] - t[first]) / update))
            for first, last in zip(cut.starts, cut.stops, strict=True)]
    n_used = int(np.sum(np.array(cut.stops) - np.array(cut.starts))) if cut.stops else 0
    return Plateaus(
        label=label,
        rate_dps=np.array(cut.rates, dtype=float),
        start=np.array(cut.starts, dtype=np.int64),
        stop=np.array(cut.stops, dtype=np.int64),
        n_transition=n - cut.in_stretch,
        n_settling=cut.in_stretch - n_used,
        ref_noise_dps=noise,
        rate_tol_dps=float(tol),
        update_s=update,
        window_s=float(window),
        settle_s=float(settle_s if settle_s is not None else DEFAULT_SETTLE_S),
        settle_source=source,
        observed_settling_s=observed,
        end_guard_s=float(end_guard),
        latency_s=float(latency_s),
        rate_changes=rate_changes,
        longest_steady_s=longest,
        n_not_settled=n_flagged,
        rate_sem_dps=np.array(sems, dtype=float),
        n_short=cut.n_short,
        sweep_dps2=sweep_rate(t, ref, window),
    )


def _window_tolerance(noise: float, per_update: float, full: float,
                      n_before: float | np.ndarray, n_after: float | np.ndarray) -> np.ndarray:
    """Tolerance of the change between two window medians, deg/s.

    Noise of a window median: ~1.25 σ/√(independent updates in it), for each side; a window
    thinned by lost rows is noisier, so its tolerance is wider.
    """
    eff_b = np.clip(n_before * per_update, 1.0, full)
    eff_a = np.clip(n_after * per_update, 1.0, full)
    return np.maximum(TOL_FLOOR_DPS, TOL_SIGMAS * 1.2533 * noise * np.sqrt(1 / eff_b + 1 / eff_a))


def _steady_stretches(
    t: np.ndarray, ref: np.ndarray, window: float, noise: float, update: float, row_s: float,
    rate_tol: float | None, row_step: float | None = None,
) -> tuple[list[tuple[int, int]], float, int]:
    """Runs of rows where the reference's windowed median holds still: (stretches, the tolerance
    for a full window, how many times the rate changed)."""
    before, after, grid_t, rows_before, rows_after = window_medians(t, ref, window, row_step=row_step)
    per_update = row_s / update
    full = max(1.0, window / update)
    tol_grid: float | np.ndarray
    if rate_tol is not None:
        tol = tol_grid = rate_tol
    else:
        tol = float(_window_tolerance(noise, per_update, full, full / per_update, full / per_update))
        tol_grid = _window_tolerance(noise, per_update, full, rows_before, rows_after)
    steady_grid = np.abs(after - before) <= tol_grid
    moving_starts = np.flatnonzero(np.diff(steady_grid.astype(np.int8)) == -1)
    rate_changes = int(moving_starts.size + (not steady_grid[0]))
    # A row is steady when the grid points on both sides of it are. The grid rises strictly, so
    # the first point at or after a row is the last at or before it when that is the row's
    # time, else the next: one search, not two.
    at_or_before = np.searchsorted(grid_t, t, side="right")
    on_point = grid_t[np.maximum(at_or_before - 1, 0)] == t
    right = np.clip(at_or_before - (on_point & (at_or_before > 0)), 0, grid_t.size - 1)
    left = np.clip(at_or_before - 1, 0, grid_t.size - 1)
    stretches = _runs(steady_grid[left] & steady_grid[right])
    if noise == 0.0:
        stretches = _exact_edges(ref, stretches)
    return stretches, tol, rate_changes


def _narrowed_by_flag(
    stretches: list[tuple[int, int]], flag: np.ndarray
) -> tuple[list[tuple[int, int]], int]:
    """The stretches cut to the rows the table flags settled (never joined or widened), and how
    many steady rows the flag left out."""
    narrowed = []
    n_flagged = 0
    for a, b in stretches:
        n_flagged += int(np.count_nonzero(~flag[a:b]))
        narrowed += [(a + c, a + d) for c, d in _runs(flag[a:b])]
    return narrowed, n_flagged


def _start_guard(settle_s: float | None, observed: float | None, noise: float,
                 window: float) -> tuple[float | None, str]:
    """The start guard and where it came from: given, observed settling, or (None) the default."""
    if settle_s is not None:
        return settle_s, "given"
    if observed is not None:
        # A noisy reference places a stretch's start only to within half a window.
        return max(observed, SETTLE_FLOOR_S, 0.0 if noise == 0.0 else window / 2), "observed"
    return None, "default"


@dataclass(frozen=True)
class _Guards:
    """What is cut from each steady stretch: the start (None: by its length) and the end, s."""

    settle_s: float | None
    end_s: float
    slack: float  # a logger's timestamp jitter must not move a plateau's ends by a row


@dataclass
class _Cut:
    """The plateaus cut from the steady stretches, in time order."""

    rates: list[float]
    starts: list[int]
    stops: list[int]
    in_stretch: int  # rows in any steady stretch
    n_short: int  # stretches shorter than the minimum, not flickers


def _cut_plateaus(t: np.ndarray, ref: np.ndarray, stretches: list[tuple[int, int]], guards: _Guards, *,
                  min_duration_s: float, window: float, tol: float) -> _Cut:
    """Each long enough stretch less its guards, with its rate (a robust mean of the reference)."""
    cut = _Cut([], [], [], 0, 0)
    for a, b in stretches:
        cut.in_stretch += b - a
        duration = float(t[b - 1] - t[a])
        if duration < min_duration_s:
            cut.n_short += duration >= window / 2  # a stretch, not a flicker between two ramps
            continue
        settle = (guards.settle_s if guards.settle_s is not None
                  else max(DEFAULT_SETTLE_S, SETTLE_FRACTION * duration))
        first = a + int(np.searchsorted(t[a:b], t[a] + settle - guards.slack, side="left"))
        last = a + int(np.searchsorted(t[a:b], t[b - 1] - guards.end_s + guards.slack, side="right"))
        if last - first < 2:
            continue
        cut.rates.append(_robust_mean(ref[first:last], tol))
        cut.starts.append(first)
        cut.stops.append(last)
    return cut


def observed_settling_s(t: np.ndarray, raw: np.ndarray, stretches: list[tuple[int, int]],
                        min_duration_s: float, row_s: float, end_guard_s: float = 0.0) -> float | None:
    """How long the sensor takes to settle after a rate change, as the session shows it, s.

    Per steady stretch: the sensor's final level and noise are the median and spread of its
    second half; its level, averaged over a short window from the stretch's start, must stay
    within ``SETTLE_SIGMAS`` standard errors of that final level; the settling time is where
    the last window outside that band (in the first half) ends. Ringing of the table that a
    commanded reference cannot show, and a slow sensor filter, both appear here. Pooled over
    the stretches by their upper quartile. None when no stretch is long enough to tell.
    """
    m = max(MIN_SETTLE_ROWS, round(SETTLE_WINDOW_S / row_s))
    times = []
    for a, b in stretches:
        b = a + int(np.searchsorted(t[a:b], t[b - 1] - end_guard_s, side="right"))  # not the next ramp
        if b - a < 2 or t[b - 1] - t[a] < min_duration_s or b - a < 4 * m:
            continue
        x, tt = raw[a:b], t[a:b] - t[a]
        tail = x[tt >= tt[-1] / 2]
        final = float(np.median(tail))
        sigma = mad_sigma(tail, final)
        if sigma == 0.0:  # a quantised, noiseless output: within one step
            sigma = float(np.min(np.abs(np.diff(np.unique(tail))), initial=1.0))
        csum = np.concatenate(([0.0], np.cumsum(x - final)))
        level = (csum[m:] - csum[:-m]) / m  # window k covers rows k..k+m-1
        first_half = tt[: level.size] < tt[-1] / 2
        outside = np.flatnonzero(first_half & (np.abs(level) > SETTLE_SIGMAS * sigma / np.sqrt(m)))
        times.append(float(tt[outside[-1] + m - 1]) if outside.size else 0.0)
    return float(np.quantile(times, SETTLE_QUANTILE)) if times else None


def window_medians(
    t: np.ndarray, ref: np.ndarray, window: float, min_rows: int = MIN_WINDOW_ROWS,
    row_step: float | None = None,
) -> tuple[np.ndarray, ...]:
    """Median of the reference over the window before and after each point of a time grid.

    Returns (median before, median after, grid times, rows before, rows after).
    Over rows, not a resampled signal: a burst of lost rows then shrinks a window rather
    than filling it with one held value. A window with fewer than ``min_rows`` rows takes the
    nearest ``min_rows`` on its side, so a rate change hidden in a gap still shows.
    ``row_step``: the rows' median step where the caller has it, as for :func:`reference_update_s`.
    """
    step = window / GRID_PER_WINDOW
    # Half a row off the rows' own clock, so timestamps jittered by a logger fall on the same side.
    offset = 0.5 * (median_step(t, 0.0) if row_step is None else row_step)
    grid_t = np.arange(t[0] + offset, t[-1] + step, step)
    lo = np.searchsorted(t, grid_t - window, side="left")
    mid = np.searchsorted(t, grid_t, side="left")
    hi = np.searchsorted(t, grid_t + window, side="left")
    n = t.size
    lo = np.minimum(lo, np.maximum(mid - min_rows, 0))
    hi = np.maximum(hi, np.minimum(mid + min_rows, n))
    before = ranged_medians(ref, lo, mid)
    after = ranged_medians(ref, mid, hi)
    # At the session's ends one side is empty: nothing is seen changing there.
    before = np.where(np.isnan(before), after, before)
    after = np.where(np.isnan(after), before, after)
    n_before, n_after = mid - lo, hi - mid
    rows_before = np.where(n_before > 0, n_before, n_after)
    rows_after = np.where(n_after > 0, n_after, n_before)
    return before, after, grid_t, rows_before, rows_after


#: Elements per block of windows taken at once: bounds the memory of the vectorised medians (8 MB:
#: a block the allocator reuses, not fresh pages each time).
MEDIAN_BLOCK = 1 << 20


def ranged_medians(x: np.ndarray, starts: np.ndarray, stops: np.ndarray) -> np.ndarray:
    """``np.median(x[a:b])`` for every pair, NaN where the range is empty.

    The same values as one median per range, without a Python call per range: ranges of equal
    length are medians along the rows of a strided view, in blocks of ``MEDIAN_BLOCK`` elements.
    A long session has hundreds of thousands of windows but only a few distinct lengths.
    """
    out = np.full(starts.shape, np.nan)
    lengths = stops - starts
    for length in np.unique(lengths[lengths > 0]):
        at = np.flatnonzero(lengths == length)
        rows = np.lib.stride_tricks.sliding_window_view(x, int(length))
        per_block = max(1, MEDIAN_BLOCK // int(length))
        for k in range(0, at.size, per_block):
            chunk = at[k:k + per_block]
            # the gathered windows are a copy of this loop's own: partitioned where they are
            out[chunk] = np.median(rows[starts[chunk]], axis=1, overwrite_input=True)
    return out


def _exact_edges(ref: np.ndarray, stretches: list[tuple[int, int]]) -> list[tuple[int, int]]:
    """For a noiseless reference, start each steady stretch at the first row of exactly its value.

    Such a reference (the commanded rate) shows the row where each plateau begins; the window
    only finds it to within half a window. The end is not widened: a held or late reference
    shows the next change only after its hold and latency, which a noiseless reference with
    instantaneous steps does not reveal; the half window kept there covers them.
    """
    same = np.concatenate(([False], np.diff(ref) == 0))  # row equals the one before
    out = []
    for a, b in stretches:
        while a > 0 and same[a]:
            a -= 1
        out.append((a, b))
    return out


def _runs(mask: np.ndarray) -> list[tuple[int, int]]:
    """[start, stop) index pairs of the True runs of a boolean array."""
    edges = np.diff(np.concatenate(([0], mask.astype(np.int8), [0])))
    return list(zip(np.flatnonzero(edges == 1).tolist(), np.flatnonzero(edges == -1).tolist(), strict=True))


def _robust_mean(values: np.ndarray, tol: float) -> float:
    """Mean of the values near their median: efficient for jitter, deaf to a stray outlier."""
    mid = float(np.median(values))
    spread = mad_sigma(values, mid)
    near = np.abs(values - mid) <= max(4.0 * spread, tol)
    return float(np.mean(values[near]))


#: A reference whose net change over one window exceeds this many times its own noise (and the
#: tolerance) is sweeping: a jittering one's net change is about its noise whatever the window.
SWEEP_NOISES = 5.0


def sweep_rate(t: np.ndarray, ref: np.ndarray, window_s: float) -> float:
    """The reference's median net change per second over successive windows (deg/s²).

    A noisy reference jitters about a level, so its net change over a window is about its
    noise whatever the window; a sweep's grows with the window. Compared with the reference's
    noise it tells a session that never stands still from one whose reference is noisy.
    """
    if t.size < 2 or window_s <= 0 or t[-1] - t[0] < 2 * window_s:
        return 0.0
    edges = np.arange(t[0], t[-1], window_s)
    at = np.clip(np.searchsorted(t, edges), 0, t.size - 1)
    return float(np.median(np.abs(np.diff(ref[at])))) / window_s


def explain_too_few(p: Plateaus, *, min_duration_s: float, what: str, why_not_sweep: str = "") -> str:
    """One line for a session where too little was found: what was seen, which option helps.

    ``why_not_sweep``: why a sweeping session could not be calibrated from windows instead
    (:mod:`canical.calibrate.sweep_windows`), said before the advice.
    """
    seen = (
        f"longest steady stretch {p.longest_steady_s:.3g} s, reference noise {p.ref_noise_dps:.3g} deg/s "
        f"(tolerance {p.rate_tol_dps:.3g} deg/s), {p.rate_changes} rate changes"
    )
    if p.n_not_settled:
        seen += f", {p.n_not_settled} steady rows flagged not settled by the table"
    if p.sweeping:
        hint = (f"the reference never stands still: it moves {p.sweep_dps2:.3g} deg/s every second (a "
                f"continuous sweep, not a noisy reference){why_not_sweep}; record the rates as steps, each "
                f"held for at least {p.window_s + DEFAULT_SETTLE_S:.3g} s")
    elif p.longest_steady_s < p.window_s:
        hint = f"a larger --rate-tol than {p.rate_tol_dps:.3g} deg/s would accept a noisier reference"
    elif p.n_short:
        hint = f"--min-plateau below {min_duration_s:g} s would accept {p.n_short} shorter stretches"
    elif p.n_not_settled:
        hint = ("the table's settled flag (--settled-column, TABLE_REF.TableSettled) left out the rest: "
                "check it")
    else:
        hint = "a shorter --settle (or --min-plateau) would keep more, or the session needs more table rates"
    return f"{what}: {seen}; {hint}"


def plateau_means(values: np.ndarray, plateaus: Plateaus) -> np.ndarray:
    """Mean of a per-sample array over each plateau's used samples."""
    return span_means(values, plateaus.start, plateaus.stop)


def span_means(values: np.ndarray, start: np.ndarray, stop: np.ndarray) -> np.ndarray:
    """Mean of a per-sample array over each ``[start, stop)`` span, from one cumulative sum."""
    csum = np.concatenate(([0.0], np.cumsum(values, dtype=float)))
    sums = csum[stop] - csum[start]
    means: np.ndarray = sums / (stop - start)
    return means


def plateau_stds(values: np.ndarray, plateaus: Plateaus) -> np.ndarray:
    """Sample standard deviation of a per-sample array over each plateau."""
    mean = plateau_means(values, plateaus)
    sq = plateau_means(values * values, plateaus)
    n = plateaus.stop - plateaus.start
    var = np.maximum(sq - mean * mean, 0.0) * n / np.maximum(n - 1, 1)
    std: np.ndarray = np.sqrt(var)
    return std
