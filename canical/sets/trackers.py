"""The state a term keeps between samples, and the stateless gate, one sample or a block at a time.

Apart from :mod:`canical.sets.term_kinds` so that the simulator and the closed loop can use the
same trackers as the run time without the registry, and so that the registry can build them
without importing the term record. Every block form does exactly what its one-sample form does
in a loop, so the corrector's ``correct`` and ``correct_one`` agree sample for sample.
"""

from __future__ import annotations

import math

import numpy as np


def rate_gate(dv: np.ndarray, knee_raw: float) -> np.ndarray:
    """g = max(|ΔV| − k, 0)/|ΔV|: 0 up to the knee, rising towards 1 beyond it.

    Times ΔV (the scale form) this is a hinge, sign(ΔV)·max(|ΔV| − k, 0): continuous
    at the knee, so the knee can be estimated by a smooth search.
    """
    a = np.abs(np.asarray(dv, dtype=float))
    gate: np.ndarray = np.maximum(a - knee_raw, 0.0) / np.maximum(a, knee_raw)
    return gate


def gate_one(dv: float, knee_raw: float) -> float:
    """:func:`rate_gate` for one sample, with the same operations in the same order."""
    a = abs(dv)
    return max(a - knee_raw, 0.0) / max(a, knee_raw)


def direction_state(raw: np.ndarray, threshold: float, state: DirectionTracker | None = None) -> np.ndarray:
    """+1/−1/0 per sample: the direction of the last change of ``raw`` larger than ``threshold``.

    ``state`` carries on a stream from its previous block (fresh when None).
    """
    tracker = state or DirectionTracker(threshold)
    out = np.empty(len(raw))
    for i, v in enumerate(np.asarray(raw, dtype=float).tolist()):
        out[i] = tracker.update(v)
    return out


def direction_steps(values: np.ndarray, threshold: float) -> np.ndarray:
    """:func:`direction_state` from a fresh state, the same values, found a flip at a time.

    Why: the per-sample tracker costs half a microsecond a sample, seconds on a session of
    millions; between flips the state is constant and the next flip is the first sample that
    moves ``threshold`` from the extreme since the last flip, which numpy finds on a window.
    The comparisons are the tracker's, on the same floats, so the result is the same bit for bit.
    """
    v = np.asarray(values, dtype=float)
    out = np.empty(len(v))
    threshold = float(threshold)
    start, state = 0, 0.0
    while start < len(v):
        flip, new_state = _next_flip(v, start, state, threshold)
        out[start:flip] = state
        if flip == len(v):
            break
        out[flip] = new_state
        start, state = flip + 1, new_state
    return out


def _next_flip(v: np.ndarray, start: int, state: float, threshold: float) -> tuple[int, float]:
    """The index of the first flip at or after ``start`` and the state it flips to (len(v): none).

    From rest both extremes run from the first sample (a rise is looked for first); after a flip
    only the extreme since the flip sample ``start - 1`` counts, and only the way back.
    """
    low = math.inf if state >= 0.0 else float(v[start - 1])
    high = -math.inf if state <= 0.0 else float(v[start - 1])
    width = 256
    while start < len(v):
        w = v[start : start + width]
        if state <= 0.0:
            lows = np.fmin.accumulate(np.concatenate(([low], w)))[1:]
            up = w - lows > threshold
        if state >= 0.0:
            highs = np.fmax.accumulate(np.concatenate(([high], w)))[1:]
            down = highs - w > threshold
        hits = up | down if state == 0.0 else (up if state < 0.0 else down)
        if hits.any():
            i = int(np.argmax(hits))
            return start + i, (1.0 if state < 0.0 or (state == 0.0 and up[i]) else -1.0)
        if state <= 0.0:
            low = float(lows[-1])
        if state >= 0.0:
            high = float(highs[-1])
        start += len(w)
        width = min(width * 2, 1 << 20)
    return len(v), state


class DirectionTracker:
    """Hysteresis on the raw signal: flips only after a move of ``threshold`` from the last extreme."""

    __slots__ = ("high", "low", "state", "threshold")

    def __init__(self, threshold: float) -> None:
        self.threshold = float(threshold)
        self.state = 0.0
        self.low = math.inf
        self.high = -math.inf

    def update(self, value: float) -> float:
        if value > self.high:
            self.high = value
        if value < self.low:
            self.low = value
        if self.state <= 0.0 and value - self.low > self.threshold:
            self.state = 1.0
            self.high = value
        elif self.state >= 0.0 and self.high - value > self.threshold:
            self.state = -1.0
            self.low = value
        return self.state


def slope_state(raw: np.ndarray, time_s: np.ndarray, tau_s: float,
                state: SlopeTracker | None = None) -> np.ndarray:
    """Smoothed d(raw)/dt per sample, as :class:`SlopeTracker` computes it one sample at a time.

    ``state`` carries on a stream from its previous block (fresh when None).
    """
    tracker = state or SlopeTracker(tau_s)
    return np.array([tracker.update(r, t) for r, t in zip(raw.tolist(), time_s.tolist(), strict=True)])


#: Samples the per-sample slope takes at once: its Python floats (some 100 bytes a sample) stay
#: a few megabytes whatever the record's length.
SLOPE_BLOCK = 1 << 16


def _slope_state_in_blocks(raw: np.ndarray, time_s: np.ndarray, tau_s: float) -> np.ndarray:
    """:func:`slope_state` of a whole record from a fresh state, bit for bit, a block at a time.

    Why: the tracker's method call per sample costs seconds on millions of samples, and its
    lists of Python floats as long as the record cost gigabytes. The differences and quotients
    are numpy's (the same IEEE operations on the same floats); the smoothing runs in a plain
    loop with ``math.exp`` as :meth:`SlopeTracker.update` does, skipping a sample whose time does
    not advance (``t - last_t > 0`` exactly when ``t > last_t``, NaN neither).
    """
    out = np.empty(raw.size)
    if raw.size == 0:
        return out
    with np.errstate(divide="ignore", invalid="ignore"):  # a step that does not advance is skipped
        dt = np.diff(time_s)
        quotient = np.diff(raw) / dt
    tau = float(tau_s)
    exp = math.exp
    value = 0.0
    out[0] = value
    for a in range(0, dt.size, SLOPE_BLOCK):
        values = []
        for d, q in zip(dt[a : a + SLOPE_BLOCK].tolist(), quotient[a : a + SLOPE_BLOCK].tolist(),
                        strict=True):
            if d > 0.0:
                value += (1.0 - exp(-d / tau)) * (q - value)
            values.append(value)
        out[a + 1 : a + 1 + len(values)] = values
    return out


class SlopeTracker:
    """Rate of change of the raw output, first-order smoothed with time constant ``tau_s``."""

    __slots__ = ("last_raw", "last_t", "tau", "value")

    def __init__(self, tau_s: float) -> None:
        self.tau = float(tau_s)
        self.value = 0.0
        self.last_raw: float | None = None
        self.last_t = 0.0

    def update(self, raw: float, t: float) -> float:
        if self.last_raw is not None and t > self.last_t:
            dt = t - self.last_t
            alpha = 1.0 - math.exp(-dt / self.tau)
            self.value += alpha * ((raw - self.last_raw) / dt - self.value)
        self.last_raw, self.last_t = raw, t
        return self.value


def slope_filter(raw: np.ndarray, time_s: np.ndarray, tau_s: float) -> np.ndarray:
    """:func:`slope_state` for a whole record, vectorised over its stretches of even spacing.

    Why: the closed loop's blocks need the slope of sessions of millions of samples, where the
    per-sample tracker takes tens of seconds. The same first-order smoothing of the same
    differences; over a long stretch of evenly spaced samples (all of an even record; the bulk of
    one whose last mean is of fewer rows, or that has a gap) with the smoothing factor of the
    median spacing (as :func:`lag_filter`), so equal to the tracker's within rounding, not bit for
    bit; the other samples one at a time, as the tracker does. The run-time corrector keeps the
    tracker.
    """
    raw = np.asarray(raw, dtype=float)
    time_s = np.asarray(time_s, dtype=float)
    if raw.size < 3:
        return slope_state(raw, time_s, tau_s)
    dt = np.diff(time_s)
    step = float(np.median(dt))
    if not step > 0:
        return _slope_state_in_blocks(raw, time_s, tau_s)
    even = np.abs(dt - step) <= 1e-6 * step
    if np.count_nonzero(even) < EVEN_RUN:
        return _slope_state_in_blocks(raw, time_s, tau_s)
    a = 1.0 - math.exp(-step / tau_s)
    with np.errstate(divide="ignore", invalid="ignore"):  # a step that does not advance is skipped
        quotient = np.diff(raw) / dt
    out = np.empty_like(raw)
    out[0] = value = 0.0
    edges = np.flatnonzero(np.diff(even.astype(np.int8))) + 1
    for lo, hi in zip([0, *edges.tolist()], [*edges.tolist(), dt.size], strict=True):
        if even[lo] and hi - lo >= EVEN_RUN:
            y = one_pole(quotient[lo:hi], a, value)
        else:  # uneven, or too short a stretch to be worth a filter call: the tracker's steps
            y = np.empty(hi - lo)
            for i, (d, q) in enumerate(zip(dt[lo:hi].tolist(), quotient[lo:hi].tolist(), strict=True)):
                if d > 0.0:
                    value += (1.0 - math.exp(-d / tau_s)) * (q - value)
                y[i] = value
        out[lo + 1 : hi + 1] = y
        value = float(y[-1])
    return out


#: Evenly spaced steps a stretch needs to be filtered at once (shorter ones go sample by sample).
EVEN_RUN = 64


class ChannelTracker:
    """First-order lag y of a channel (time constant τ, exact for any sample spacing).

    ``derivative`` false: y − reference (a lag term); true: (v − y)/τ, which is dy/dt,
    the channel's rate of change smoothed over τ (a derivative term). For the first τ of
    a stream, y is the plain mean of the samples seen so far: starting from the first
    sample alone would carry that one sample's noise for τ, an exponential decay that
    looks like a warm-up. Block and per-sample paths start alike.
    """

    __slots__ = ("count", "derivative", "last_t", "reference", "start_t", "tau", "y")

    def __init__(self, tau_s: float, reference: float = 0.0, derivative: bool = False) -> None:
        self.tau = float(tau_s)
        self.reference = float(reference)
        self.derivative = derivative
        self.y: float | None = None
        self.start_t = 0.0
        self.last_t = 0.0
        self.count = 0

    def update(self, value: float, t: float) -> float:
        if self.y is None:
            self.y, self.start_t, self.count = value, t, 1
        elif t - self.start_t < self.tau:
            self.count += 1
            self.y += (value - self.y) / self.count
        elif t > self.last_t:
            self.y += (1.0 - math.exp(-(t - self.last_t) / self.tau)) * (value - self.y)
        self.last_t = t
        return (value - self.y) / self.tau if self.derivative else self.y - self.reference


def lag_filter(values: np.ndarray, time_s: np.ndarray, tau_s: float) -> np.ndarray:
    """The lag y :class:`ChannelTracker` computes, for a whole record (a mean, then a lag).

    Vectorised when the samples after the first τ are evenly spaced (the usual
    case); sample by sample otherwise.
    """
    values = np.asarray(values, dtype=float)
    time_s = np.asarray(time_s, dtype=float)
    if values.size < 2:
        return values.copy()
    in_mean = time_s - time_s[0] < tau_s  # the tracker's test, sample by sample
    k = max(int(np.argmin(in_mean)) if not in_mean.all() else values.size, 1)  # samples in the mean
    if in_mean[k:].any() or not np.all(np.isfinite(time_s)):  # time went back into the first τ
        tracker = ChannelTracker(tau_s)
        return np.array([tracker.update(v, t) for v, t in zip(values.tolist(), time_s.tolist(), strict=True)])
    out = np.empty_like(values)
    out[:k] = np.cumsum(values[:k]) / np.arange(1, k + 1)
    if k == values.size:
        return out
    dt = np.diff(time_s[k - 1 :])
    step = _even_step(dt)
    if step is not None:
        out[k:] = one_pole(values[k:], 1.0 - math.exp(-step / tau_s), float(out[k - 1]))
        return out
    # Uneven spacing (jittered or rounded time stamps, gaps): each step's own factor, as the tracker
    # takes it; a step whose time does not advance keeps the lag (factor 0).
    # In pieces of VARYING_PIECE samples, each from the last one's end: a handful of temporaries
    # of a piece stay in cache where ones as long as the record would stream through memory.
    y = float(out[k - 1])
    for a in range(0, dt.size, VARYING_PIECE):
        d = dt[a : a + VARYING_PIECE]
        log_keep = np.where(d > 0.0, -d / tau_s, 0.0)
        piece = varying_pole(-np.expm1(log_keep) * values[k + a : k + a + d.size], log_keep, y)
        out[k + a : k + a + d.size] = piece
        y = float(piece[-1])
    return out


def _even_step(dt: np.ndarray) -> float | None:
    """The median step where it is positive and every step lies within a millionth of it; else None.

    Why the spread first: the median sorts the steps, a fifth of a lag's cost on a long record
    whose binned time stamps are uneven at every block's edge; steps further apart than two
    millionths of the largest cannot all lie that close to any step.
    """
    if dt.size == 0 or not float(dt.max()) - float(dt.min()) <= 2e-6 * float(dt.max()):
        return None
    step = float(np.median(dt))
    return step if step > 0 and np.all(np.abs(dt - step) <= 1e-6 * step) else None


#: Samples :func:`lag_filter` hands :func:`varying_pole` at once.
VARYING_PIECE = 1 << 16


#: Samples a row of :func:`varying_pole` takes; and the decay (in e-folds) over a row up to which a
#: row is solved by a scaled cumulative sum (its scale factors e^600 stay far from overflow).
VARYING_ROW = 64
VARYING_SPAN = 600.0


def varying_pole(b: np.ndarray, log_keep: np.ndarray, before: float = 0.0) -> np.ndarray:
    """y[n] = b[n] + exp(log_keep[n])·y[n−1] from y[−1] = ``before`` (log_keep ≤ 0): a first-order
    smoothing whose factor changes from sample to sample (a lag on uneven time stamps).

    Why: on a session of millions of samples with jittered time stamps the tracker's Python call per
    sample is the closed loop's bottleneck (one pass per τ tried). Within a row of
    :data:`VARYING_ROW` samples y = e^L·(y₀ + cumsum(b·e^−L)), L the row's cumulative log factor
    (every term below the largest partial sum, so rounding stays relative to the result); each row's
    end is carried into the next by the same recursion on the rows' ends, e^L(row) apart. A row that
    decays by more than :data:`VARYING_SPAN` e-folds (a long gap) is stepped through in a loop.
    Equal to the tracker's steps within rounding.
    """
    b = np.asarray(b, dtype=float)
    log_keep = np.asarray(log_keep, dtype=float)
    size = VARYING_ROW
    whole = b.size - b.size % size if b.size >= 4 * size else 0
    out = np.empty(b.size)
    y = before
    if whole:
        rows_b = b[:whole].reshape(-1, size)
        cum = np.cumsum(log_keep[:whole].reshape(-1, size), axis=1)
        decay = np.exp(cum)
        ok = -cum[:, -1] <= VARYING_SPAN
        if ok.all():
            rest = decay * np.cumsum(rows_b / decay, axis=1)
        else:
            rest = np.empty_like(rows_b)
            rest[ok] = decay[ok] * np.cumsum(rows_b[ok] / decay[ok], axis=1)
            for r in np.flatnonzero(~ok).tolist():
                rest[r] = _step_pole(rows_b[r], log_keep[r * size : (r + 1) * size], 0.0)
        ends = varying_pole(rest[:, -1], cum[:, -1], before)  # each row's true end
        carry = np.concatenate(([before], ends[:-1]))
        rest += carry[:, None] * decay
        out[:whole] = rest.ravel()
        y = float(ends[-1])
    out[whole:] = _step_pole(b[whole:], log_keep[whole:], y)
    return out


def _step_pole(b: np.ndarray, log_keep: np.ndarray, before: float) -> np.ndarray:
    """:func:`varying_pole` one sample at a time (short records, a row across a long gap)."""
    out = np.empty(b.size)
    y = before
    for i, (bi, li) in enumerate(zip(b.tolist(), log_keep.tolist(), strict=True)):
        y = bi + math.exp(li) * y
        out[i] = y
    return out


#: Samples a row of :func:`one_pole`'s matrix product takes.
ONE_POLE_CHUNK = 16


def one_pole(x: np.ndarray, a: float, before: float = 0.0) -> np.ndarray:
    """y[n] = a·x[n] + (1 − a)·y[n−1] from y[−1] = ``before``: first-order smoothing of a whole
    record (``scipy.signal.lfilter([a], [1, a − 1], x, zi=[(1 − a)·before])``, equal within rounding).

    Why not lfilter: importing scipy.signal takes half a second of every calibration. The record
    is cut into rows of :data:`ONE_POLE_CHUNK` samples; one matrix product smooths every row from
    rest (its weights a·(1 − a)^k, none above 1, so nothing grows), and what each row's end carries
    into the next is the same smoothing of the rows' ends with (1 − a)^16, done the same way.
    """
    x = np.asarray(x, dtype=float)
    bad = np.flatnonzero(~np.isfinite(x))
    if bad.size:  # a row's product would spread it to the samples before it: finite up to there
        head = _smooth(x[: bad[0]], a, 1.0 - a, before)
        last = float(head[-1]) if head.size else before
        return np.concatenate((head, _smooth(x[bad[0]:], a, 1.0 - a, last)))
    return _smooth(x, a, 1.0 - a, before)


def _smooth(x: np.ndarray, gain: float, keep: float, before: float) -> np.ndarray:
    """y[n] = gain·x[n] + keep·y[n−1] from y[−1] = ``before`` (see :func:`one_pole`)."""
    size, out = ONE_POLE_CHUNK, np.empty(x.size)
    whole = x.size - x.size % size if x.size >= 4 * size else 0
    y = before
    if whole:
        j = np.arange(size)
        decay = _powers(keep, j + 1)  # decay[k] = keep^(k+1)
        lower = j[:, None] >= j[None, :]
        weights = np.where(lower, gain * _powers(keep, np.where(lower, j[:, None] - j[None, :], 0)), 0.0)
        rows = out[:whole].reshape(-1, size)
        np.matmul(x[:whole].reshape(-1, size), weights.T, out=rows)
        ends = _smooth(rows[:, -1].copy(), 1.0, float(decay[-1]), before)  # each row's true end
        rows[1:] += np.multiply.outer(ends[:-1], decay)
        rows[0] += before * decay
        y = float(ends[-1])
    for i in range(whole, x.size):
        y = gain * float(x[i]) + keep * y
        out[i] = y
    return out


def _powers(base: float, exponents: np.ndarray) -> np.ndarray:
    """base^exponents, those below 1e-300 made 0 (subnormal numbers make products crawl)."""
    p: np.ndarray = np.power(base, exponents, dtype=float)
    p[p < 1e-300] = 0.0
    return p
