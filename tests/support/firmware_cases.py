"""Coefficient sets of every model kind and every term kind, and sample streams to run them on.

Shared by the firmware tests and ``tests/benchmarks/bench_firmware_eval.py``. The rate models
are calibrated from simulated turntable sessions; the effect terms are attached with plausible
sizes (a set is data: the evaluator must follow whatever a valid set says).
"""

from __future__ import annotations

import functools
import itertools
from dataclasses import replace

import numpy as np

from canical.calibration.pipeline import CalibrateOptions, calibrate
from canical.sets import coefficient_file
from canical.sets.coefficients import CoefficientSet
from canical.sets.imu_set import ImuSet, as_matrix
from canical.sets.terms import term_from_dict
from canical.sim.imu_stream import default_gyros
from canical.sim.sessions import paper_session
from canical.sim.triad import random_triad

SERIAL = 4711
SENSOR = str(SERIAL)
AXIS = "z"
CHANNELS = ("temp_c", "supply_v")
TEMP_STEP = 0.1  # degC: the Temperature signal of canical.dbc
SUPPLY_STEP = 0.001  # V: SupplyVoltage

MODELS = {
    "segmented-inverse": CalibrateOptions(segments=3, order=3, extend=False),
    "segmented-inverse-free-joins": CalibrateOptions(segments=3, order=3, smoothness=None, extend=False),
    "segmented-inverse-order-6": CalibrateOptions(segments=5, order=6, extend=False),
    "segmented-linear": CalibrateOptions(model="segmented-linear", extend=False),
    "forward-poly": CalibrateOptions(model="forward-poly", order=3, extend=False),
}

def hermite_pieces(knots: list[float], value, slope) -> list[list[float]]:
    """The pieces (a0, a1, a2, a3 per segment, in u = v − knot) of the cubic Hermite spline through
    ``value`` with ``slope`` at the knots: a smooth curve as a spline term writes it."""
    rows = []
    for k0, k1 in itertools.pairwise(knots):
        h, y0, y1, m0, m1 = k1 - k0, value(k0), value(k1), slope(k0), slope(k1)
        d = (y1 - y0) / h
        rows.append([float(y0), float(m0), float((3 * d - 2 * m0 - m1) / h), float((m0 + m1 - 2 * d) / h**2)])
    return rows


#: A bias saturating with temperature, 60·tanh((T − 25)/10) counts, as a spline whose knots lie
#: between the Temperature signal's 0.1 °C steps (no sample sits on a knot within float32 rounding).
SPLINE_KNOTS = [4.05, 12.05, 18.05, 22.05, 25.05, 28.05, 33.05, 46.05]


def _saturating(t: float) -> float:
    return 60.0 * float(np.tanh((t - 25.0) / 10.0))


def _saturating_slope(t: float) -> float:
    return 6.0 / float(np.cosh((t - 25.0) / 10.0)) ** 2


#: ΔV knots (raw counts) of the rate spline: across the span and beyond (flat there), half a count
#: off the integers (raw counts are integers; V0 is not either).
RATE_KNOTS = [-30000.5, -15000.5, -5000.5, 0.5, 5000.5, 15000.5, 30000.5]


def _rate_shape(dv: float) -> float:
    return 1.5 * float(np.tanh(dv / 12000.0))


def _rate_shape_slope(dv: float) -> float:
    return 1.5 / 12000.0 / float(np.cosh(dv / 12000.0)) ** 2


#: Knots of the derivative spline (deg C/s): the stream's temperature changes by up to some
#: 0.05 C/s, its noise over τ = 2.5 s adds as much.
DERIVATIVE_KNOTS = [-0.1, -0.05, -0.02, 0.0, 0.02, 0.05, 0.1]


def _transient(d: float) -> float:
    return 40.0 * float(np.tanh(d / 0.04))


def _transient_slope(d: float) -> float:
    return 1000.0 / float(np.cosh(d / 0.04)) ** 2


def saturating_spline(knots: list[float]) -> dict:
    """A bias spline of temperature through 60·tanh((T − 25)/10) counts on ``knots``."""
    return {"kind": "channel", "channel": "temp_c", "feature": "spline", "form": "bias", "coefficient": 1.0,
            "knots": list(knots), "pieces": hermite_pieces(list(knots), _saturating, _saturating_slope)}


#: One term of every kind and feature; bias and scale forms alternate.
TERMS = {
    "channel-gated": {
        "kind": "channel",
        "channel": "temp_c",
        "feature": "gated",
        "form": "scale",
        "coefficient": 3e-4,
        "reference": 25.0,
        "threshold_raw": 6000.0,
    },
    "channel-offset": {
        "kind": "channel",
        "channel": "temp_c",
        "feature": "offset",
        "form": "bias",
        "coefficient": 3.1,
        "reference": 25.0,
    },
    "channel-square": {
        "kind": "channel",
        "channel": "temp_c",
        "feature": "square",
        "form": "scale",
        "coefficient": 2.5e-5,
        "reference": 20.0,
    },
    "channel-offset-supply": {
        "kind": "channel",
        "channel": "supply_v",
        "feature": "offset",
        "form": "scale",
        "coefficient": 1.5e-3,
        "reference": 12.0,
    },
    "time-warmup": {
        "kind": "time",
        "feature": "warmup",
        "form": "bias",
        "coefficient": -42.0,
        "tau_s": 300.0,
    },
    "time-linear": {"kind": "time", "feature": "linear", "form": "scale", "coefficient": 2e-7},
    "direction-sign": {
        "kind": "direction",
        "feature": "sign",
        "form": "bias",
        "coefficient": 6.5,
        "threshold_raw": 80.0,
    },
    "direction-slope": {
        "kind": "direction",
        "feature": "slope",
        "form": "bias",
        "coefficient": 2e-3,
        "tau_s": 0.05,
    },
    "channel-lag": {
        "kind": "channel",
        "channel": "temp_c",
        "feature": "lag",
        "form": "bias",
        "coefficient": 2.8,
        "reference": 25.0,
        "tau_s": 120.0,
    },
    "channel-derivative": {
        "kind": "channel",
        "channel": "temp_c",
        "feature": "derivative",
        "form": "scale",
        "coefficient": 0.02,
        "tau_s": 2.5,
    },
    "channel-direction": {  # threshold off the 1 mV grid of the IMU's supply frames: no ties
        "kind": "channel",
        "channel": "supply_v",
        "feature": "direction",
        "form": "bias",
        "coefficient": 4.5,
        "threshold_raw": 0.0375,
    },
    "channel-spline": saturating_spline(SPLINE_KNOTS),
    "channel-rate-spline": {  # a temperature coefficient that grows with rate and saturates
        "kind": "channel",
        "channel": "temp_c",
        "feature": "rate_spline",
        "form": "bias",
        "coefficient": 1.0,
        "reference": 25.0,
        "knots": RATE_KNOTS,
        "pieces": hermite_pieces(RATE_KNOTS, _rate_shape, _rate_shape_slope),
    },
    "channel-lag-spline": dict(saturating_spline(SPLINE_KNOTS), feature="lag_spline", tau_s=90.0),
    "channel-derivative-spline": {  # a thermal transient that saturates with the rate of change
        "kind": "channel",
        "channel": "temp_c",
        "feature": "derivative_spline",
        "form": "scale",
        "coefficient": 2e-5,
        "tau_s": 2.5,
        "knots": DERIVATIVE_KNOTS,
        "pieces": hermite_pieces(DERIVATIVE_KNOTS, _transient, _transient_slope),
    },
}

#: The stateful channel transforms in their other form (TERMS holds one form of each).
OTHER_FORMS = {
    "channel-lag-scale": dict(TERMS["channel-lag"], form="scale", coefficient=1e-4),
    "channel-derivative-bias": dict(TERMS["channel-derivative"], form="bias", coefficient=150.0),
    "channel-direction-scale": dict(TERMS["channel-direction"], form="scale", coefficient=3e-4),
    "channel-spline-scale": dict(TERMS["channel-spline"], form="scale", coefficient=2e-5),
    "channel-rate-spline-scale": dict(TERMS["channel-rate-spline"], form="scale", coefficient=1e-4),
    "channel-lag-spline-scale": dict(TERMS["channel-lag-spline"], form="scale", coefficient=2e-5),
    "channel-derivative-spline-bias": dict(TERMS["channel-derivative-spline"], form="bias", coefficient=1.0),
}
ALL_TERMS = {**TERMS, **OTHER_FORMS}


@functools.cache
def model_set(name: str) -> CoefficientSet:
    """A calibrated set of one model kind for the emulated IMU's z axis (serial 4711)."""
    session = paper_session(default_gyros()[AXIS], seed=3, dwell_s=3.0, sensor=SENSOR, axis=AXIS)
    return calibrate(session, MODELS[name], sensor_id=SENSOR, axis=AXIS).coefficients


def with_terms(cset: CoefficientSet, names: tuple[str, ...]) -> CoefficientSet:
    """The set with effect terms attached, validated through the file format."""
    return with_terms_dicts(cset, tuple(ALL_TERMS[n] for n in names))


def with_terms_dicts(cset: CoefficientSet, terms: tuple[dict, ...]) -> CoefficientSet:
    """The set with these term dicts attached, validated through the file format."""
    out = replace(cset, terms=tuple(term_from_dict(t) for t in terms))
    return coefficient_file.loads(coefficient_file.dumps(out))


def term_set(names: tuple[str, ...]) -> CoefficientSet:
    return with_terms(model_set("segmented-inverse"), names)


def stream(cset: CoefficientSet, n: int, seed: int = 0) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """n samples at 100 Hz: integer counts sweeping the span and 15% beyond it (so out-of-span
    samples occur at both ends), with wiggles that reverse direction, temperature, supply, time.

    Channels come at the resolution the IMU's frames carry them (as a device's ADC delivers
    them), not as arbitrary doubles: the firmware gets float32 values, and a channel-direction
    decision made within float32 rounding of its threshold can only agree with canical's double
    one if the values sit on a grid the threshold is off."""
    rng = np.random.default_rng(seed)
    lo, hi = cset.span_raw
    mid, half = 0.5 * (lo + hi), 0.5 * (hi - lo) * 1.15
    k = np.arange(n)
    sweep = np.sin(2 * np.pi * k / 60_000.0) * half
    wiggle = 400.0 * np.sin(2 * np.pi * k / 700.0) + np.cumsum(rng.normal(0.0, 6.0, n)) % 300.0
    raw = np.rint(mid + sweep + wiggle + rng.normal(0.0, 25.0, n))
    time_s = k / 100.0
    temp = 25.0 + 18.0 * np.sin(2 * np.pi * k / 250_000.0) + rng.normal(0.0, 0.05, n)
    supply = 12.0 + 0.6 * np.sin(2 * np.pi * k / 90_000.0) + rng.normal(0.0, 0.01, n)
    temp, supply = on_grid(temp, TEMP_STEP), on_grid(supply, SUPPLY_STEP)
    return raw, {"time_s": time_s, "temp_c": temp, "supply_v": supply}


def on_grid(values: np.ndarray, step: float) -> np.ndarray:
    return np.round(values / step) * step


def imu_every_term_set(seed: int = 0) -> ImuSet:
    """An IMU set whose three axes carry every term kind (the z set of :func:`term_set`, as each
    axis) and whose coupling undoes a random triad's (:mod:`canical.sim.triad`, 0.4–2 %)."""
    return imu_set_of(term_set(tuple(TERMS)), seed)


def imu_set_of(cset: CoefficientSet, seed: int = 0) -> ImuSet:
    """An IMU set with ``cset`` as each of its three axes and the coupling that undoes a random
    triad's (:mod:`canical.sim.triad`, 0.4–2 %)."""
    axes = tuple(replace(cset, axis=a) for a in "xyz")
    matrix = np.linalg.inv(random_triad(seed).coupling)
    return ImuSet(SENSOR, axes, as_matrix(matrix), as_matrix(np.full((3, 3), 1e-4)),  # type: ignore[arg-type]
                  {"coupling_plateaus": 0}, "2026-01-01T00:00:00Z")


def imu_stream(imu: ImuSet, n: int, seed: int = 0) -> tuple[np.ndarray, dict[str, np.ndarray]]:
    """n three-axis samples: each axis's raw from :func:`stream` of its own set (its own seed),
    the inputs (time, temperature, supply) shared, as one IMU's frames carry them."""
    streams = [stream(cset, n, seed=3 * seed + i) for i, cset in enumerate(imu.axes)]
    return np.column_stack([raw for raw, _ in streams]), streams[0][1]
