"""How a real rate table moves and records its rate: the session as the equipment produces it.

A simulator that only produces ideal steps with a perfect reference at the sensor's sample
rate never exercises what breaks plateau finding on real recordings. Each behaviour here is
switchable (:class:`TableBehaviour`; the defaults are the ideal table):

* rate changes limited in acceleration (``accel_dps2``, down to 1 deg/s²) and optionally in
  jerk (``jerk_dps3``: an S-curve); ``accel_dps2=None`` is an instantaneous step;
* servo overshoot with damped ringing after each rate change (``overshoot``, ``ring_hz``,
  ``ring_decay_s``): the table's true rate rings, whatever the reference shows;
* the reference as the *commanded* rate (exact, no ringing) or as the *measured* rate
  (the true rate, quantised to ``encoder_lsb_dps`` and with ``jitter_dps`` rms noise);
* the reference updated at its own rate (``ref_rate_hz``, held between updates), late by
  ``ref_latency_s``, and on its own clock (``asynchronous``: a random phase, a slightly
  different rate and jittered frame times), as table frames joined to IMU frames on a bus;
* sensor rows lost in bursts (``loss_fraction`` of the rows, bursts of ``loss_burst_s`` mean);
* the table's settled flag recorded with the session (``settled_flag``), as the table raises
  it: from its commanded rate, blind to its own ringing.

:func:`record_table` returns the whole truth (true rate at every sensor tick, which ticks
were kept, the table's frames) so tests can check what a detector used.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

REFERENCES = ("commanded", "measured")


@dataclass(frozen=True)
class TableBehaviour:
    """How the table moves between plateaus and how its rate is recorded."""

    accel_dps2: float | None = None  # None: instantaneous steps
    jerk_dps3: float | None = None  # S-curve rate changes when set
    overshoot: float = 0.0  # peak overshoot, fraction of the rate step
    ring_hz: float = 2.0
    ring_decay_s: float = 0.25  # time constant of the ringing's envelope
    reference: str = "commanded"  # or "measured"
    encoder_lsb_dps: float = 0.0  # quantisation of a measured rate
    jitter_dps: float = 0.0  # rms noise of a measured rate
    ref_rate_hz: float | None = None  # None: one reference value per sensor sample
    ref_latency_s: float = 0.0
    asynchronous: bool = False  # table frames on their own clock
    loss_fraction: float = 0.0  # fraction of sensor rows lost, in bursts
    loss_burst_s: float = 0.1  # mean burst length
    settled_flag: bool = False  # the session records the table's settled flag

    def __post_init__(self) -> None:
        if self.reference not in REFERENCES:
            raise ValueError(f"reference {self.reference!r} (known: {', '.join(REFERENCES)})")


@dataclass(frozen=True)
class Schedule:
    """The commanded programme: transition k goes to ``rates[k]`` over [start[k], end[k])."""

    rates: np.ndarray
    start: np.ndarray
    end: np.ndarray  # transition end = plateau start
    stop: np.ndarray  # plateau end = next transition's start
    initial: float

    def commanded(self, t: np.ndarray, accel: float | None, jerk: float | None) -> np.ndarray:
        """The commanded rate at times ``t``."""
        k = np.searchsorted(self.start, t, side="right") - 1
        before = np.concatenate(([self.initial], self.rates[:-1]))
        w = np.where(k < 0, self.initial, 0.0)
        inside = k >= 0
        kk = np.clip(k, 0, None)
        frm, to = before[kk], self.rates[kk]
        s = t - self.start[kk]
        frac = _transition_fraction(np.abs(to - frm), s, self.end[kk] - self.start[kk], accel, jerk)
        return np.where(inside, frm + (to - frm) * frac, w)


def transition_time(delta: float, accel: float | None, jerk: float | None) -> float:
    """Duration of a rate change of ``delta`` deg/s."""
    d = abs(delta)
    if accel is None or d == 0:
        return 0.0
    if jerk is None:
        return d / accel
    t1 = accel / jerk
    if d >= accel * t1:
        return 2 * t1 + (d / accel - t1)
    return 2 * np.sqrt(d / jerk)


def _transition_fraction(d, s, duration, accel, jerk):
    """Fraction of the change done ``s`` seconds into a transition of ``d`` deg/s."""
    d = np.asarray(d, dtype=float)
    s = np.clip(s, 0.0, duration)
    safe_d = np.where(d > 0, d, 1.0)
    if accel is None:
        return np.ones_like(s)
    if jerk is None:
        return np.where(duration > 0, s * accel / safe_d, 1.0).clip(0, 1)
    t1 = np.minimum(accel / jerk, np.sqrt(d / jerk))
    a = jerk * t1
    tc = duration - 2 * t1
    v = np.where(
        s < t1,
        jerk * s**2 / 2,
        np.where(s < t1 + tc, a * t1 / 2 + a * (s - t1), d - jerk * (duration - s) ** 2 / 2),
    )
    return np.where(d > 0, v / safe_d, 1.0).clip(0, 1)


def schedule(rates_dps, dwell_s: float, behaviour: TableBehaviour, t0_s: float = 0.0,
             initial_dps: float | None = None) -> Schedule:
    """Transition and plateau times of a programme (starting at ``initial_dps``, else the first rate)."""
    rates = np.asarray(rates_dps, dtype=float)
    current = float(rates[0]) if initial_dps is None else float(initial_dps)
    start, end, stop = [], [], []
    t = t0_s
    for r in rates:
        start.append(t)
        t += transition_time(r - current, behaviour.accel_dps2, behaviour.jerk_dps3)
        end.append(t)
        t += dwell_s
        stop.append(t)
        current = float(r)
    initial = float(rates[0]) if initial_dps is None else float(initial_dps)
    return Schedule(rates, np.array(start), np.array(end), np.array(stop), initial)


def ringing(t: np.ndarray, sched: Schedule, behaviour: TableBehaviour) -> np.ndarray:
    """The servo's overshoot and damped ringing after each rate change, deg/s."""
    out = np.zeros_like(t)
    if behaviour.overshoot <= 0:
        return out
    omega = 2 * np.pi * behaviour.ring_hz
    tau = behaviour.ring_decay_s
    s_peak = np.arctan(omega * tau) / omega
    peak = np.exp(-s_peak / tau) * np.sin(omega * s_peak)
    before = np.concatenate(([sched.initial], sched.rates[:-1]))
    for delta, e in zip(sched.rates - before, sched.end, strict=True):
        if delta == 0:
            continue
        s = t - e
        on = (s >= 0) & (s < 12 * tau)
        out[on] += behaviour.overshoot * delta / peak * np.exp(-s[on] / tau) * np.sin(omega * s[on])
    return out


@dataclass(frozen=True)
class TableRecording:
    """A session's table side: sensor ticks, the truth, and what was recorded."""

    time_s: np.ndarray  # every sensor tick (before any loss)
    true_dps: np.ndarray  # the table's true rate at each tick (ringing included)
    commanded_dps: np.ndarray  # the commanded rate at each tick
    ref_dps: np.ndarray  # the reference as recorded with each tick (held, late, noisy)
    settled: np.ndarray  # the table's settled flag as recorded with each tick
    kept: np.ndarray  # bool per tick: row not lost
    frame_time_s: np.ndarray  # the table's reference frames: times...
    frame_dps: np.ndarray  # ...their rate...
    frame_settled: np.ndarray  # ...and their settled flag
    schedule: Schedule


def record_table(
    rates_dps,
    *,
    dwell_s: float,
    fs_hz: float,
    behaviour: TableBehaviour,
    rng: np.random.Generator,
    t0_s: float = 0.0,
    initial_dps: float | None = None,
) -> TableRecording:
    """Simulate the table through a programme and record it as ``behaviour`` says."""
    b = behaviour
    sched = schedule(rates_dps, dwell_s, b, t0_s, initial_dps)
    n = int(np.floor((sched.stop[-1] - t0_s) * fs_hz))
    t = t0_s + np.arange(n) / fs_hz
    accel, jerk = b.accel_dps2, b.jerk_dps3
    commanded = sched.commanded(t, accel, jerk)
    true = commanded + ringing(t, sched, b)
    # The table's frames: one per sensor tick, or at their own rate (own clock when asynchronous).
    if b.ref_rate_hz is None:
        ft = t.copy()
    else:
        rate = b.ref_rate_hz * (1 + (2e-4 if b.asynchronous else 0.0))
        phase = rng.uniform(0, 1 / rate) if b.asynchronous else 0.0
        ft = t0_s + phase + np.arange(int((t[-1] - t0_s) * rate) + 1) / rate
        if b.asynchronous:
            ft = np.sort(ft + rng.uniform(-0.1, 0.1, ft.size) / rate)
    sample_at = ft - b.ref_latency_s
    cmd_at = sched.commanded(sample_at, accel, jerk)
    if b.reference == "commanded":
        fw = cmd_at
    else:
        fw = cmd_at + ringing(sample_at, sched, b) + b.jitter_dps * rng.standard_normal(ft.size)
        if b.encoder_lsb_dps > 0:
            fw = np.round(fw / b.encoder_lsb_dps) * b.encoder_lsb_dps
    # Settled: the table's own flag, from its commanded rate (the servo cannot see its ringing).
    k = np.searchsorted(sched.start, sample_at, side="right") - 1
    fs_flag = (k >= 0) & (sample_at >= sched.end[np.clip(k, 0, None)])
    # Each tick records the latest frame received by then (held between frames).
    latest = np.searchsorted(ft, t, side="right") - 1
    latest = np.clip(latest, 0, None)
    ref = fw[latest]
    settled = fs_flag[latest]
    kept = lost_in_bursts(n, fs_hz, b.loss_fraction, b.loss_burst_s, rng)
    return TableRecording(t, true, commanded, ref, settled, kept, ft, fw, fs_flag, sched)


def lost_in_bursts(n: int, fs_hz: float, fraction: float, burst_s: float, rng: np.random.Generator):
    """Mask of kept rows when ``fraction`` of them are lost in bursts of ``burst_s`` mean length."""
    kept = np.ones(n, dtype=bool)
    if fraction <= 0 or n == 0:
        return kept
    mean_len = max(1.0, burst_s * fs_hz)
    target = round(fraction * n)
    while (~kept).sum() < target:
        length = int(max(1, rng.exponential(mean_len)))
        start = int(rng.integers(0, n))
        kept[start : start + length] = False
    return kept
