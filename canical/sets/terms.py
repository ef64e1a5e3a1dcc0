"""Effect terms: what the closed loop adds to a rate model, evaluated at run time.

Effects act on the sensor's output, so their correction is applied there, in
raw units, before the rate model: for a term with feature x,

* ``bias`` form:  ΔV' = ΔV − c·x        (c in raw units per unit of x),
* ``scale`` form: ΔV' = ΔV − c·x·ΔV     (c: relative gain error per unit of x),

and then ω = f(ΔV'). Correcting in the rate domain instead would be wrong by
the slope variation of f (a few per cent for a nonlinear sensor) times the
effect. The coefficient is the sensor's own error, so a positive temperature
coefficient means the output rises with temperature. Features:

* ``channel`` — an auxiliary signal by name, minus its reference value:
  ``offset`` x = v − ref, ``square`` x = (v − ref)²; and, with state (the sensor
  feels the channel late or through its changes; input ``time_s`` too for the
  first two): ``lag`` x = y − ref where y follows v through a first-order lag of
  time constant τ (the die is where the effect acts, the channel reads elsewhere),
  ``derivative`` x = (v − y)/τ, the rate of change of v smoothed with τ (a thermal
  transient; for the first τ of a stream y is the mean of the samples so far),
  ``direction`` x = ±1, the sign of the last change of v larger than
  ``threshold_raw`` in the channel's own units (hysteresis: heating vs cooling);
  and, stateless but reading the raw output too, ``gated`` x = (v − ref)·g with
  g = max(|ΔV| − k, 0)/|ΔV| and the knee k = ``threshold_raw`` in raw units: an
  effect that acts only beyond some rate (a drive loop near its limit). In scale
  form c·x·ΔV = c·(v − ref)·sign(ΔV)·max(|ΔV| − k, 0), a hinge; in bias form a
  bias that switches on with rate;
* ``time`` — time since power-on t (input ``time_s``): ``warmup`` x = 1 − exp(−t/τ),
  ``linear`` x = t;
* ``direction`` — how the rate got where it is. ``sign``: the direction of the last
  significant change of the raw output (x = +1 after a rise, −1 after a fall, 0
  before either), a hysteresis tracker with a threshold in raw units. ``slope``:
  the rate of change of the raw output (raw units per second, smoothed with time
  constant τ; input ``time_s``). Both have state, so samples must come in time order.

Terms are plain dicts in the coefficient file (see :data:`TERM_FIELDS`); this
module validates them and evaluates their features, vectorised or one sample at
a time.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass
from typing import Any

import numpy as np

TIME_INPUT = "time_s"
FEATURES = {
    "channel": ("offset", "square", "lag", "derivative", "direction", "gated"),
    "time": ("warmup", "linear"),
    "direction": ("sign", "slope"),
}
FORMS = ("bias", "scale")
STATEFUL_CHANNEL = ("lag", "derivative", "direction")
TERM_FIELDS = ("kind", "channel", "feature", "form", "coefficient", "reference", "tau_s", "threshold_raw")


@dataclass(frozen=True)
class Term:
    """One validated term."""

    kind: str
    feature: str
    form: str
    coefficient: float
    channel: str | None = None
    reference: float = 0.0
    tau_s: float | None = None
    threshold_raw: float | None = None

    @property
    def input_name(self) -> str | None:
        """The run-time input this term reads first (None: derived from raw alone)."""
        if self.kind == "channel":
            return self.channel
        if self.kind == "time" or self.feature == "slope":
            return TIME_INPUT
        return None

    @property
    def input_names(self) -> tuple[str, ...]:
        """Every run-time input this term reads: a lag or derivative needs time as well."""
        first = self.input_name
        if first is None:
            return ()
        if self.kind == "channel" and self.feature in ("lag", "derivative"):
            return (first, TIME_INPUT)
        return (first,)

    def describe(self) -> str:
        """A readable name for reports: ``d/dt temp_c``, ``lag(temp_c, τ=140 s)``."""
        if self.kind == "channel" and self.feature == "gated":
            return f"{self.channel} × (|ΔV| > {self.threshold_raw:.0f} counts)"
        if self.kind == "channel":
            return channel_feature_name(self.feature, self.channel or "?", self.tau_s)
        if self.kind == "time":
            return f"warm-up (τ={self.tau_s:.0f} s)" if self.feature == "warmup" else "linear drift"
        return "direction of approach" if self.feature == "sign" else "rate of change of raw"

    def to_dict(self) -> dict[str, Any]:
        return {
            "kind": self.kind,
            "channel": self.channel,
            "feature": self.feature,
            "form": self.form,
            "coefficient": self.coefficient,
            "reference": self.reference,
            "tau_s": self.tau_s,
            "threshold_raw": self.threshold_raw,
        }


def term_from_dict(d: Mapping[str, Any], where: str = "term") -> Term:
    """Validate a term dict; raises ValueError with a message naming the field."""
    kind = d.get("kind")
    if kind not in FEATURES:
        raise ValueError(f"{where}: kind {kind!r} not supported by this canical version")
    feature = d.get("feature")
    if feature not in FEATURES[kind]:
        raise ValueError(
            f"{where}: feature {feature!r} not valid for kind {kind} ({', '.join(FEATURES[kind])})"
        )
    form = d.get("form")
    if form not in FORMS:
        raise ValueError(f"{where}: form {form!r} must be bias or scale")

    def number(key: str, required: bool = False, positive: bool = False) -> float | None:
        v = d.get(key)
        if v is None and not required:
            return None
        if not isinstance(v, int | float) or isinstance(v, bool) or not math.isfinite(v):
            raise ValueError(f"{where}: {key} must be a finite number")
        if positive and v <= 0:
            raise ValueError(f"{where}: {key} must be positive")
        return float(v)

    channel = d.get("channel")
    if kind == "channel" and (not isinstance(channel, str) or not channel):
        raise ValueError(f"{where}: channel must name an input")
    stateful = kind == "channel" and feature in STATEFUL_CHANNEL
    tau = number("tau_s", required=feature in ("warmup", "slope", "lag", "derivative"), positive=True)
    threshold = number("threshold_raw", required=feature in ("sign", "gated")
                       or (stateful and feature == "direction"), positive=True)
    return Term(
        kind=kind,
        feature=feature,
        form=form,
        coefficient=number("coefficient", required=True),  # type: ignore[arg-type]
        channel=channel if kind == "channel" else None,
        reference=number("reference") or 0.0,
        tau_s=tau,
        threshold_raw=threshold,
    )


def channel_feature_name(feature: str, channel: str, tau_s: float | None = None) -> str:
    """How a report names a channel transform (a gated one: see :func:`gated_name`)."""
    if feature == "gated":
        return gated_name(channel)
    if feature == "offset":
        return f"channel:{channel}"
    if feature == "square":
        return f"({channel})²"
    if feature == "derivative":
        return f"d/dt {channel}"
    if feature == "direction":
        return f"sign d/dt {channel}"
    return f"lag({channel}, τ={tau_s:.0f} s)" if tau_s else f"lag({channel})"


def gated_name(channel: str, knee_dps: float | None = None) -> str:
    """``temp_c × (|rate| > 30 dps)``; without a knee, the candidate's name (knee to be estimated)."""
    knee = "knee" if knee_dps is None else f"{knee_dps:.0f} dps"
    return f"{channel} × (|rate| > {knee})"


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


def feature_values(
    term: Term, inputs: Mapping[str, np.ndarray], raw: np.ndarray, dv: np.ndarray | None = None
) -> np.ndarray:
    """The term's feature x for a block of samples in time order (fresh state).

    ``dv`` (raw − V0) is needed by a gated term only.
    """
    if term.feature == "gated":
        if dv is None:
            raise ValueError("a gated term needs ΔV = raw − V0")
        x = _column(inputs, term.channel) - term.reference
        gated: np.ndarray = x * rate_gate(dv, term.threshold_raw or 1.0)
        return gated
    if term.kind == "channel" and term.feature in STATEFUL_CHANNEL:
        values = _column(inputs, term.channel)
        if term.feature == "direction":
            return direction_state(values, term.threshold_raw or 1.0)
        tracker = ChannelTracker(term)
        time_s = np.asarray(inputs[TIME_INPUT], dtype=float)
        return np.array([tracker.update(v, t) for v, t in zip(values.tolist(), time_s.tolist(), strict=True)])
    if term.feature == "sign":
        return direction_state(raw, term.threshold_raw or 1.0)
    if term.feature == "slope":
        return slope_state(raw, np.asarray(inputs[TIME_INPUT], dtype=float), term.tau_s or 1.0)
    values = _column(inputs, term.input_name)
    if term.kind == "channel":
        x = values - term.reference
        return x * x if term.feature == "square" else x
    if term.feature == "warmup":
        assert term.tau_s is not None  # term_from_dict requires τ of a warm-up term
        warm: np.ndarray = 1.0 - np.exp(-values / term.tau_s)
        return warm
    return values


def _column(inputs: Mapping[str, np.ndarray], name: str | None) -> np.ndarray:
    """An input as floats; every term that reads one names it (term_from_dict checks)."""
    if name is None:
        raise ValueError("the term reads no input")
    return np.asarray(inputs[name], dtype=float)


def direction_state(raw: np.ndarray, threshold: float, state: DirectionTracker | None = None) -> np.ndarray:
    """+1/−1/0 per sample: the direction of the last change of ``raw`` larger than ``threshold``."""
    tracker = state or DirectionTracker(threshold)
    out = np.empty(len(raw))
    for i, v in enumerate(np.asarray(raw, dtype=float).tolist()):
        out[i] = tracker.update(v)
    return out


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


def slope_state(raw: np.ndarray, time_s: np.ndarray, tau_s: float) -> np.ndarray:
    """Smoothed d(raw)/dt per sample, as :class:`SlopeTracker` computes it one sample at a time."""
    tracker = SlopeTracker(tau_s)
    return np.array([tracker.update(r, t) for r, t in zip(raw.tolist(), time_s.tolist(), strict=True)])


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


class ChannelTracker:
    """First-order lag y of a channel (time constant τ, exact for any sample spacing).

    Feature ``lag``: y − reference; feature ``derivative``: (v − y)/τ, which is dy/dt,
    the channel's rate of change smoothed over τ. For the first τ of a stream, y is
    the plain mean of the samples seen so far: starting from the first sample alone
    would carry that one sample's noise for τ, an exponential decay that looks like a
    warm-up. Block and per-sample paths start alike.
    """

    __slots__ = ("count", "derivative", "last_t", "reference", "start_t", "tau", "y")

    def __init__(self, term: Term) -> None:
        self.tau = float(term.tau_s or 1.0)
        self.reference = float(term.reference)
        self.derivative = term.feature == "derivative"
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
    k = int(np.searchsorted(time_s - time_s[0], tau_s, side="left"))  # samples in the mean
    k = max(k, 1)
    out = np.empty_like(values)
    out[:k] = np.cumsum(values[:k]) / np.arange(1, k + 1)
    if k == values.size:
        return out
    dt = np.diff(time_s[k - 1 :])
    step = float(np.median(dt))
    if step > 0 and np.all(np.abs(dt - step) <= 1e-6 * step):
        from scipy.signal import lfilter  # here: the daemon (canical serve) must not load scipy

        a = 1.0 - np.exp(-step / tau_s)
        out[k:] = lfilter([a], [1.0, a - 1.0], values[k:], zi=[(1.0 - a) * out[k - 1]])[0]
        return out
    tracker = ChannelTracker(Term("channel", "lag", "bias", 0.0, channel="_", tau_s=tau_s))
    return np.array([tracker.update(v, t) for v, t in zip(values.tolist(), time_s.tolist(), strict=True)])


def raw_shift(terms: tuple[Term, ...], features: np.ndarray, dv: np.ndarray) -> np.ndarray:
    """Σ c·x (bias) + Σ c·x·ΔV (scale): what the effects add to ΔV, for a block of samples.

    ``features`` holds one column per term (the feature x of each sample).
    """
    shift = np.zeros_like(dv, dtype=float)
    for j, term in enumerate(terms):
        x = features[:, j]
        shift = shift + term.coefficient * (x * dv if term.form == "scale" else x)
    return shift
