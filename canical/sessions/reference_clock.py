"""A rate table's own recording put on the sensor's clock: offset and drift from the rate changes both show.

A table controller logs its rate to its own file, stamped by its own clock: another epoch
(an offset of hours or of the Unix time) and a crystal a few tens of ppm off the logger's
(drift). The sensor's log has no table rate, but its raw output changes exactly when the
table's rate does, so the two recordings can be lined up on those changes alone:

* **Coarse**: both are smoothed onto a common time grid and differentiated; the lags where
  the table's rate changes and the sensor's output changes correlate best are candidate
  offsets. Drift is searched too, in steps small enough that it never smears a change by
  more than a fraction of the smoothing. A programme of equal steps correlates nearly as
  well shifted by one step, so the best few peaks are all refined.
* **Fine**: each rate change the table shows is matched on its own, in a window around it,
  by the lag where the sensor's output best follows the table's rate (an affine fit: the
  sensor's scale and bias do not matter; its nonlinearity is nearly affine over one change).
  Steps are located by their edges, ramps by their corners.
* **Offset and drift** are then a robust least-squares line through those lags against time.
  Of the candidates, the one matching the most rate changes inside the session wins (the
  ends of a programme tell its shifts apart: shifted, one change falls outside or finds no
  partner). Two matching as many are **ambiguous** (a repeating programme, the sensor
  recording only part of the table's file): refused, as are too few shared changes.

The table's rate is joined to the sensor's samples as bus frames would be: each sample
holds the latest table row as of its instant (so plateau finding sees a held reference,
as it does for a CAN log). Samples outside the table's file have no reference and are
left out. Pure numpy; errors are one line saying why the files cannot be aligned.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import numpy as np

from canical.errors import CanicalError
from canical.models.robust_stats import mad_sigma

GRID_S = 0.05  # common grid of the coarse search
SMOOTH_S = 0.25  # each grid point is the mean over this window
MAX_DRIFT_PPM = 1000.0  # clock rate errors searched (crystals are within ±100 ppm)
CANDIDATES = 3  # coarse alignments refined: the best and those nearly as good
CANDIDATE_SHARE = 0.8  # ...correlating at least this share of the best
MAIN_LOBE = 0.5  # the best peak's lobe: lags where the correlation stays above half of it
EVENT_SIGMAS = 8.0  # the table's rate is changing where its derivative exceeds this many sigmas
MERGE_S = 0.5  # changes closer than this are one rate change
MAX_PAD_S = 2.0  # steady time kept on each side of a change for matching it
MIN_PAD_S = 0.3
SEARCH_S = 0.5  # fine lags searched around the coarse alignment, s
COARSE_STEP_S = 0.01
FINE_STEP_S = 0.0005
MIN_FIT = 0.5  # a change matches when the sensor follows the table's rate this well (r²) there
MIN_EVENTS = 3  # matched rate changes needed (offset, drift and a check)
OUTLIER_SIGMAS = 4.0
STEP_SHARE = 0.9  # a change is one step when one row-to-row jump carries this much of it
MIN_HALF_WIDTH_S = 0.0025  # rows this close (200 Hz) locate a step as well as the sensor does


@dataclass(frozen=True)
class TableTrace:
    """The table's rate as its own file records it: times on the table's clock."""

    time_s: np.ndarray
    ref_dps: np.ndarray
    source: str


@dataclass(frozen=True)
class ClockFit:
    """Table time = ``offset_s + (1 + drift_ppm·1e-6) · session time``; and how well it is known."""

    offset_s: float
    drift_ppm: float
    events: int  # rate changes matched and used
    rejected: int  # rate changes matched but off the line (outliers)
    residual_s: float  # rms of the matched changes' lags about the fitted line
    overlap_s: float  # session time covered by the table's file
    unmatched: int = 0  # the table's rate changes inside the session the sensor does not follow

    def to_table(self, session_s: np.ndarray) -> np.ndarray:
        return self.offset_s + (1.0 + self.drift_ppm * 1e-6) * np.asarray(session_s, dtype=float)

    @property
    def residual_ms(self) -> float:
        return 1e3 * self.residual_s

    def describe(self) -> dict[str, float | int]:
        """For report.json."""
        return {
            "offset_s": self.offset_s,
            "drift_ppm": self.drift_ppm,
            "rate_changes_matched": self.events,
            "rate_changes_off_the_line": self.rejected,
            "rate_changes_unmatched": self.unmatched,
            "residual_ms": self.residual_ms,
            "overlap_s": self.overlap_s,
        }


@dataclass(frozen=True)
class ReferenceClock:
    """A table's own file put on the session's clock: which file, the fit, and the session's
    samples it does not cover (left out). The command prints it and the report writes it, both
    from this record; report.json's form is :meth:`to_dict`."""

    file: str
    fit: ClockFit
    samples_outside: int

    def to_dict(self) -> dict[str, str | float | int]:
        return {"file": self.file, **self.fit.describe(), "samples_outside": self.samples_outside}


@dataclass(frozen=True)
class JoinedReference:
    """The table's rate held at each session sample, and which samples the table's file covers."""

    ref_dps: np.ndarray
    inside: np.ndarray  # bool per sample


@dataclass(frozen=True)
class _Coarse:
    offset_s: float
    drift: float  # fraction, not ppm


def align_reference(time_s: np.ndarray, raw: np.ndarray, table: TableTrace) -> ClockFit:
    """Offset and drift of the table's clock against the session's, from the rate changes both show.

    Each alignment the coarse search finds nearly as good as its best is refined; the one whose
    line matches the most of the table's rate changes inside the session (less those it cannot
    match) wins. A tie is ambiguous: a repeating programme seen only in part.
    """
    t = np.asarray(time_s, dtype=float)
    x = np.asarray(raw, dtype=float)
    tt = np.asarray(table.time_s, dtype=float)
    ref = np.asarray(table.ref_dps, dtype=float)
    if tt.size < 4 or t.size < 4:
        raise CanicalError(f"{table.source}: cannot align: too few rows to show rate changes")
    events = table_events(tt, ref)
    if not events:
        raise CanicalError(f"{table.source}: cannot align: the table's rate never changes "
                           "(no rate changes to line up with the sensor's)")
    scored: list[tuple[int, ClockFit]] = []
    failure = ""
    for coarse in coarse_alignments(t, x, tt, ref, table.source):
        try:
            fit = refined(t, x, tt, ref, events, coarse, table.source)
        except CanicalError as exc:
            failure = failure or str(exc)
            continue
        scored.append((fit.events + fit.rejected - fit.unmatched, fit))
    if not scored:
        raise CanicalError(failure)
    scored.sort(key=lambda s: -s[0])
    best = scored[0][1]
    if len(scored) > 1 and scored[1][0] == scored[0][0]:
        other = scored[1][1]
        raise CanicalError(
            f"{table.source}: cannot align: ambiguous: the table's clock offset by {best.offset_s:.4f} s "
            f"and by {other.offset_s:.4f} s each match {scored[0][0]} rate changes (a repeating programme, "
            "or a table file covering more than the log): trim the table's file to the session or vary "
            "the steps or dwells")
    return best


def refined(t: np.ndarray, x: np.ndarray, tt: np.ndarray, ref: np.ndarray,
            events: list[tuple[float, float]], coarse: _Coarse, source: str) -> ClockFit:
    """One coarse alignment refined on the rate changes inside the session."""
    fit = ClockFit(coarse.offset_s, coarse.drift * 1e6, 0, 0, 0.0, 0.0)
    inside = [e for e in events if _covered(fit, t, e)]
    if len(inside) < MIN_EVENTS:
        raise CanicalError(
            f"{source}: cannot align: too little overlap: at the best alignment the log shares "
            f"{_overlap_s(fit, t, tt):.3g} s and {len(inside)} rate changes with the table's file "
            f"(at least {MIN_EVENTS} are needed)")
    for _ in range(2):  # the second pass searches around the first one's line
        fit = refine(t, x, tt, ref, inside, fit, source)
    return fit


def table_events(tt: np.ndarray, ref: np.ndarray) -> list[tuple[float, float]]:
    """(start, end) on the table's clock of each rate change its file shows."""
    grid, level = smoothed_grid(tt, ref, tt[0], tt[-1])
    d = np.diff(level)
    noise = _robust_sigma(d)
    floor = 1e-4 * float(np.max(np.abs(d), initial=0.0))
    moving = np.abs(d) > max(EVENT_SIGMAS * noise, floor, 1e-12)
    edges = np.diff(np.concatenate(([0], moving.astype(np.int8), [0])))
    runs = list(zip(np.flatnonzero(edges == 1), np.flatnonzero(edges == -1), strict=True))
    merged: list[list[float]] = []
    for a, b in runs:
        start, end = float(grid[a]), float(grid[b])
        if merged and start - merged[-1][1] < MERGE_S:
            merged[-1][1] = end
        else:
            merged.append([start, end])
    return [(a, b) for a, b in merged]


def smoothed_grid(t: np.ndarray, x: np.ndarray, start: float, stop: float,
                  step: float = GRID_S, scale: float = 1.0) -> tuple[np.ndarray, np.ndarray]:
    """Mean of ``x`` over ``SMOOTH_S`` around each point of a grid (``scale``: grid step in ``t``'s units).

    Means of the rows in each window, by cumulative sums: rows lost or unevenly spaced change
    nothing; windows without a row take the neighbours' values.
    """
    grid = start + step * scale * np.arange(max(2, int((stop - start) / (step * scale)) + 1))
    half = SMOOTH_S * scale / 2
    csum = np.concatenate(([0.0], np.cumsum(x)))
    lo = np.searchsorted(t, grid - half, side="left")
    hi = np.searchsorted(t, grid + half, side="right")
    count = hi - lo
    full = count > 0
    level = np.empty(grid.size)
    level[full] = (csum[hi[full]] - csum[lo[full]]) / count[full]
    if not full.all():
        level[~full] = np.interp(grid[~full], t, x)
    return grid, level


def coarse_alignments(t: np.ndarray, x: np.ndarray, tt: np.ndarray, ref: np.ndarray,
                      source: str) -> list[_Coarse]:
    """Offsets (and the drift) where the sensor's and the table's rate changes correlate best:
    the best, then other peaks nearly as high (a shifted programme of equal steps)."""
    _, table_level = smoothed_grid(tt, ref, tt[0], tt[-1])
    a = np.diff(table_level)
    duration = float(t[-1] - t[0])
    drift_step = SMOOTH_S / 8 / max(duration, 1.0)
    n_drift = int(np.ceil(MAX_DRIFT_PPM * 1e-6 / drift_step))
    best: tuple[float, float, np.ndarray, int] | None = None
    for drift in drift_step * np.arange(-n_drift, n_drift + 1):
        # The sensor's grid runs at the table's grid step in table time.
        _, level = smoothed_grid(t, x, t[0], t[-1], scale=1.0 / (1.0 + drift))
        b = np.diff(level)
        c = np.abs(_cross_correlation(a, b))
        k = int(np.argmax(c))
        if best is None or c[k] > best[0]:
            best = (float(c[k]), float(drift), c, b.size)
    assert best is not None
    peak, drift, c, n_b = best
    if peak == 0.0:
        raise CanicalError(f"{source}: cannot align: the sensor's output shows no rate changes")
    return [_Coarse(float(tt[0] + (k - (n_b - 1)) * GRID_S - (1.0 + drift) * t[0]), drift)
            for k in _peaks(c)]


def _cross_correlation(a: np.ndarray, b: np.ndarray) -> np.ndarray:
    """``c[k] = Σ_j b[j]·a[j + k - (len(b) - 1)]`` for every overlap, by FFT."""
    n = a.size + b.size - 1
    size = 1 << (n - 1).bit_length()
    c = np.fft.irfft(np.fft.rfft(a, size) * np.conj(np.fft.rfft(b, size)), size)
    return np.concatenate((c[size - (b.size - 1):], c[: a.size])) if b.size > 1 else c[: a.size]


def _peaks(c: np.ndarray) -> list[int]:
    """The highest peak of ``c`` and up to ``CANDIDATES - 1`` others at least ``CANDIDATE_SHARE``
    of its height, each outside the others' lobes (where ``c`` stays above half its peak)."""
    mag = c.copy()
    top = float(mag.max())
    found: list[int] = []
    while len(found) < CANDIDATES:
        k = int(np.argmax(mag))
        if found and mag[k] < CANDIDATE_SHARE * top:
            break
        found.append(k)
        low = mag < MAIN_LOBE * mag[k]
        left, right = np.flatnonzero(low[:k]), np.flatnonzero(low[k:])
        mag[(int(left[-1]) if left.size else 0):(k + int(right[0]) if right.size else mag.size)] = 0.0
    return found


def refine(t: np.ndarray, x: np.ndarray, tt: np.ndarray, ref: np.ndarray,
           events: list[tuple[float, float]], fit: ClockFit, source: str) -> ClockFit:
    """Each rate change matched on its own, then a robust line through their lags.

    Where every matched change is a step the table recorded between two rows, each lag is
    known only to within half the rows' spacing (the step happened somewhere between them):
    the line is then the one that stays deepest inside all those intervals, which a table
    whose rows fall at varying phases of its steps narrows far below one row's spacing.
    """
    centres, lags, halves = [], [], []
    for i, (start, end) in enumerate(events):
        before = start - events[i - 1][1] if i else MAX_PAD_S
        after = events[i + 1][0] - end if i + 1 < len(events) else MAX_PAD_S
        pad_lo = min(MAX_PAD_S, max(MIN_PAD_S, 0.45 * before))
        pad_hi = min(MAX_PAD_S, max(MIN_PAD_S, 0.45 * after))
        lag = event_lag(t, x, tt, ref, fit, start - pad_lo, end + pad_hi)
        if lag is not None:
            centres.append(_to_session(fit, (start + end) / 2))
            lags.append(lag)
            halves.append(step_half_width(tt, ref, start, end))
    if len(lags) < MIN_EVENTS:
        raise CanicalError(
            f"{source}: cannot align: the sensor's output follows only {len(lags)} of the table's "
            f"{len(events)} rate changes in the overlap (at least {MIN_EVENTS} are needed): "
            "is it the right table file and the right signal?")
    tc, lag_s = np.asarray(centres), np.asarray(lags)
    keep = np.ones(tc.size, dtype=bool)
    for _ in range(3):
        slope, intercept = np.polyfit(tc[keep], lag_s[keep], 1) if keep.sum() > 2 else (0.0, np.mean(lag_s))
        resid = lag_s - (intercept + slope * tc)
        spread = max(_robust_sigma(resid[keep]), 1e-4)
        keep = np.abs(resid) <= OUTLIER_SIGMAS * spread
    half = np.asarray(halves)[keep]
    if np.all(half > 0) and np.median(half) > MIN_HALF_WIDTH_S:
        intercept, slope = deepest_line(tc[keep], lag_s[keep], half, float(intercept), float(slope))
        resid = lag_s - (intercept + slope * tc)
    scale = 1.0 + fit.drift_ppm * 1e-6 + slope
    offset = fit.offset_s + intercept
    used = int(keep.sum())
    result = ClockFit(float(offset), float((scale - 1.0) * 1e6), used, tc.size - used,
                      float(np.sqrt(np.mean(resid[keep] ** 2))), 0.0)
    return replace(result, unmatched=len(events) - tc.size, overlap_s=_overlap_s(result, t, tt))


def step_half_width(tt: np.ndarray, ref: np.ndarray, start: float, end: float) -> float:
    """Half the spacing of the two rows a step fell between; 0 when the change is not one step."""
    rows = np.flatnonzero((tt >= start - SMOOTH_S) & (tt <= end + SMOOTH_S))
    if rows.size < 2:
        return 0.0
    d = np.diff(ref[rows])
    j = int(np.argmax(np.abs(d)))
    total = ref[rows[-1]] - ref[rows[0]]
    if total == 0 or abs(d[j]) < STEP_SHARE * abs(total):
        return 0.0
    return float(tt[rows[j] + 1] - tt[rows[j]]) / 2


def deepest_line(tc: np.ndarray, lag: np.ndarray, half: np.ndarray, intercept: float,
                 slope: float) -> tuple[float, float]:
    """The line (intercept, slope) deepest inside every interval ``lag ± half``: the largest
    smallest margin, by a grid search that zooms in around the least-squares line."""
    centre = float(np.mean(tc))
    a0 = intercept + slope * centre  # intercept at the centre: the two are then nearly independent
    span = max(float(np.ptp(tc)), 1.0)
    da, db = float(np.max(half)), 2 * float(np.max(half)) / span
    best = (a0, slope)
    for _ in range(4):
        a = best[0] + da * np.linspace(-1, 1, 41)
        b = best[1] + db * np.linspace(-1, 1, 41)
        pred = a[:, None, None] + b[None, :, None] * (tc - centre)[None, None, :]
        margin = np.min(half - np.abs(lag - pred), axis=2)
        i, j = np.unravel_index(int(np.argmax(margin)), margin.shape)
        best = (float(a[i]), float(b[j]))
        da, db = da / 10, db / 10
    return best[0] - best[1] * centre, best[1]


def event_lag(t: np.ndarray, x: np.ndarray, tt: np.ndarray, ref: np.ndarray, fit: ClockFit,
              lo: float, hi: float) -> float | None:
    """How far the table's clock is off ``fit`` at one rate change, s; None when it does not match.

    The lag where the sensor's output over the window best follows the table's rate
    (linear between its rows) by an affine fit: scanned coarsely over ``±SEARCH_S``, then finely.
    """
    mapped = fit.to_table(t)
    sel = (mapped >= lo) & (mapped <= hi)
    if np.count_nonzero(sel) < 10:
        return None
    u, y = mapped[sel], x[sel]
    coarse = np.arange(-SEARCH_S, SEARCH_S + COARSE_STEP_S / 2, COARSE_STEP_S)
    r2 = _affine_r2(u, y, tt, ref, coarse)
    k = int(np.argmax(r2))
    if r2[k] < MIN_FIT or k in (0, coarse.size - 1):
        return None
    fine = coarse[k] + np.arange(-2 * COARSE_STEP_S, 2 * COARSE_STEP_S + FINE_STEP_S / 2, FINE_STEP_S)
    r2 = _affine_r2(u, y, tt, ref, fine)
    j = int(np.argmax(r2))
    lag = float(fine[j])
    if 0 < j < fine.size - 1:  # parabola through the peak
        den = r2[j - 1] - 2 * r2[j] + r2[j + 1]
        if den < 0:
            lag += FINE_STEP_S * 0.5 * float(r2[j - 1] - r2[j + 1]) / float(den)
    return lag


def _affine_r2(u: np.ndarray, y: np.ndarray, tt: np.ndarray, ref: np.ndarray,
               lags: np.ndarray) -> np.ndarray:
    """Per lag: r² of the sensor's output against the table's rate at ``u + lag``."""
    r = np.interp(u[None, :] + lags[:, None], tt, ref)
    r = r - r.mean(axis=1, keepdims=True)
    yc = y - y.mean()
    cov = r @ yc
    var_r = np.einsum("ij,ij->i", r, r)
    var_y = float(yc @ yc)
    with np.errstate(invalid="ignore", divide="ignore"):
        out = np.where(var_r > 0, cov * cov / (var_r * var_y), 0.0) if var_y > 0 else np.zeros(lags.size)
    return np.asarray(out)


def join_reference(time_s: np.ndarray, table: TableTrace, fit: ClockFit) -> JoinedReference:
    """The table's rate at each session sample: its latest row as of then, as a bus would hold it.

    A sample before the table's first row, or later than one row interval after its last,
    has no reference.
    """
    tt = np.asarray(table.time_s, dtype=float)
    at = fit.to_table(time_s)
    idx = np.searchsorted(tt, at, side="right") - 1
    step = float(np.median(np.diff(tt))) if tt.size > 1 else 0.0
    inside = (idx >= 0) & (at <= tt[-1] + step)
    ref = np.asarray(table.ref_dps, dtype=float)[np.clip(idx, 0, tt.size - 1)]
    return JoinedReference(ref, inside)


def _to_session(fit: ClockFit, table_s: float) -> float:
    return (table_s - fit.offset_s) / (1.0 + fit.drift_ppm * 1e-6)


def _covered(fit: ClockFit, t: np.ndarray, event: tuple[float, float]) -> bool:
    """Whether a rate change falls inside the session, with room to match it."""
    start, end = fit.to_table(np.array([t[0], t[-1]]))
    return bool(event[0] - MIN_PAD_S >= start and event[1] + MIN_PAD_S <= end)


def _overlap_s(fit: ClockFit, t: np.ndarray, tt: np.ndarray) -> float:
    start, end = fit.to_table(np.array([t[0], t[-1]]))
    return float(max(0.0, min(end, tt[-1]) - max(start, tt[0])) / (1.0 + fit.drift_ppm * 1e-6))


def _robust_sigma(x: np.ndarray) -> float:
    if x.size == 0:
        return 0.0
    return mad_sigma(x)
