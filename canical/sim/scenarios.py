"""Sessions with undeclared effects, and what a model that knew the effect would use.

Each scenario names the effects the simulated sensor has, the auxiliary
channels recorded (distractors included), the order of table rates, and the
answer the closed loop should reach: the candidate(s) to attribute, nothing, or
a confounded pair. ``oracle_terms`` are the term forms of the true effect, for
measuring how close the loop comes to a model that was told.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field, replace

import numpy as np

from canical.sessions.session import Session
from canical.sets.term_kinds import (
    CHANNEL_DERIVATIVE,
    CHANNEL_DERIVATIVE_SPLINE,
    CHANNEL_DIRECTION,
    CHANNEL_GATED,
    CHANNEL_LAG,
    CHANNEL_LAG_SPLINE,
    CHANNEL_OFFSET,
    CHANNEL_RATE_SPLINE,
    CHANNEL_SPLINE,
    CHANNEL_SQUARE,
    DIRECTION,
    DIRECTION_SIGN,
    TIME_LINEAR,
    TIME_WARMUP,
    TermKind,
)
from canical.sets.terms import Term
from canical.sim import effects as fx
from canical.sim import environment as env
from canical.sim.gyro import Effect, GyroModel
from canical.sim.sessions import paper_rates, sweep_session
from canical.sim.table_recording import TableBehaviour


@dataclass(frozen=True)
class Scenario:
    name: str
    effects: tuple[Effect, ...]
    aux: dict[str, Callable] = field(default_factory=dict)
    profile: str = "shuffled"  # shuffled | up-down | ascending
    gyro: GyroModel | None = None  # noise and nonlinearity (default GyroModel()); effects are added
    expect: tuple[str, ...] = ()  # candidate names the loop must attribute
    # Other attributions that are as right: a nested form that ties with the expected one.
    also_right: tuple[tuple[str, ...], ...] = ()
    confounded: tuple[str, ...] = ()  # candidate names it must report as confounded
    oracle_terms: tuple[Term, ...] = ()
    # The effect is not fully representable by any candidate: the loop must say a residual
    # stays unexplained (as it must when it leaves a confounded pair out).
    leaves_residual: bool = False

    def attributed(self, found: tuple[str, ...]) -> bool:
        """Whether the effects found are the expected attribution (or one as right)."""
        return set(found) in [set(self.expect), *map(set, self.also_right)]

    def rates(self, seed: int) -> np.ndarray:
        base = paper_rates()
        if self.profile == "shuffled":
            return np.random.default_rng(seed).permutation(np.repeat(base, 2))
        if self.profile == "up-down":
            return np.concatenate([base, base[::-1], base, base[::-1]])
        return np.concatenate([base, base])

    def session(self, seed: int = 0, dwell_s: float = 10.0, table: TableBehaviour | None = None) -> Session:
        """The scenario's session; ``table`` records it as a real table would (ramps, jitter...)."""
        gyro = replace(self.gyro or GyroModel(), effects=self.effects)
        return sweep_session(gyro, self.rates(seed), dwell_s=dwell_s, seed=seed, aux=self.aux, table=table)


def _t(spec: TermKind, form: str, **kw) -> Term:
    return Term.of(spec, form, 0.0, **kw)


DISTRACTORS = {"noise_ch": env.white_noise(3.0, 1.0), "wander": env.random_walk(0.02)}
TEMP_STEPS = {"temp_c": env.temperature_steps(), **DISTRACTORS}
SUPPLY_STEPS = {"supply_v": env.supply_steps(), "temp_c": env.temperature_steps((24.0, 25.0, 26.0)),
                **DISTRACTORS}
T_BIAS = _t(CHANNEL_OFFSET, "bias", channel="temp_c", reference=25.0)
T_SCALE = _t(CHANNEL_OFFSET, "scale", channel="temp_c", reference=25.0)
T_SQUARE = _t(CHANNEL_SQUARE, "bias", channel="temp_c", reference=25.0)
V_BIAS = _t(CHANNEL_OFFSET, "bias", channel="supply_v", reference=5.0)
V_SCALE = _t(CHANNEL_OFFSET, "scale", channel="supply_v", reference=5.0)
WARM = _t(TIME_WARMUP, "bias", tau_s=200.0)
WARM_SCALE = _t(TIME_WARMUP, "scale", tau_s=200.0)
DRIFT = _t(TIME_LINEAR, "bias")
DIR = _t(DIRECTION_SIGN, "bias", threshold_raw=400.0)
# Environments for effects in forms nobody listed.
# A transient follows the true temperature's rate of change, not its readout noise:
# these temperature readouts are averaged (as on-die sensors are), noise 0.002 C.
TEMP_CYCLE = {"temp_c": env.temperature_cycle(noise_c=0.002), **DISTRACTORS}
TEMP_HOLD_STEPS = {"temp_c": env.temperature_steps((10.0, 20.0, 30.0, 40.0), period_s=90.0,
                                                   time_constant_s=15.0, noise_c=0.02), **DISTRACTORS}
TEMP_SLOW_STEPS = {"temp_c": env.temperature_steps(period_s=150.0, time_constant_s=20.0), **DISTRACTORS}
TEMP_TRIANGLE = {"temp_c": env.temperature_triangle(), **DISTRACTORS}
TWO_AXIS = {"raw_x": env.other_axis_raw(), **DISTRACTORS}
# Clean-sensor checks: five channels that carry nothing, one of them slowly varying.
FIVE_DISTRACTORS = {"noise_a": env.white_noise(3.0, 1.0), "noise_b": env.white_noise(0.0, 0.2),
                    "wander_a": env.random_walk(0.02), "wander_b": env.random_walk(0.005, 10.0),
                    "room_c": env.temperature_cycle(22.0, 2.0, (2400.0, 1300.0), 0.02)}
T_RATE = _t(CHANNEL_DERIVATIVE, "bias", channel="temp_c", tau_s=3.0)
T_LAG = _t(CHANNEL_LAG, "bias", channel="temp_c", tau_s=120.0)
T_LAG60 = _t(CHANNEL_LAG, "bias", channel="temp_c", tau_s=60.0)
T_LAG60_SCALE = _t(CHANNEL_LAG, "scale", channel="temp_c", tau_s=60.0)
T_HYST = _t(CHANNEL_DIRECTION, "bias", channel="temp_c", threshold_raw=1.0)
X_LEAK = _t(CHANNEL_OFFSET, "bias", channel="raw_x")
# Knee 30 dps at the simulated 400 counts per deg/s (the loop estimates it, told or not).
T_GATED = _t(CHANNEL_GATED, "scale", channel="temp_c", reference=25.0, threshold_raw=12_000.0)
COLOURED = GyroModel(bias_instability_dps=0.003, rate_random_walk_dps_rt_s=1e-4)

SCENARIOS: tuple[Scenario, ...] = (
    Scenario("temperature bias 0.01 dps/C, chamber steps",
             (fx.TemperatureEffect(bias_dps_per_c=0.01),), TEMP_STEPS,
             expect=("channel:temp_c",), oracle_terms=(T_BIAS,)),
    Scenario("temperature bias 0.003 dps/C (small), chamber steps",
             (fx.TemperatureEffect(bias_dps_per_c=0.003),), TEMP_STEPS,
             expect=("channel:temp_c",), oracle_terms=(T_BIAS,)),
    Scenario("temperature bias + scale 200 ppm/C, chamber steps",
             (fx.TemperatureEffect(bias_dps_per_c=0.01, scale_per_c=2e-4),), TEMP_STEPS,
             expect=("channel:temp_c",), oracle_terms=(T_BIAS, T_SCALE)),
    Scenario("temperature quadratic bias, chamber steps",
             (fx.TemperatureEffect(bias_dps_per_c=0.004, bias_dps_per_c2=3e-4),), TEMP_STEPS,
             expect=("channel:temp_c",), oracle_terms=(T_BIAS, T_SQUARE)),
    Scenario("warm-up 0.3 dps, tau 200 s",
             (fx.WarmupEffect(0.3, 200.0),), DISTRACTORS,
             expect=("time:warm-up",), oracle_terms=(WARM,)),
    Scenario("warm-up 0.08 dps, tau 200 s (small)",
             (fx.WarmupEffect(0.08, 200.0),), DISTRACTORS,
             expect=("time:warm-up",), oracle_terms=(WARM,)),
    Scenario("warm-up bias + scale",
             (fx.WarmupEffect(0.2, 200.0, scale_amplitude=0.004),), DISTRACTORS,
             expect=("time:warm-up",), oracle_terms=(WARM, WARM_SCALE)),
    Scenario("supply 0.2 dps/V, supply steps",
             (fx.SupplyEffect(bias_dps_per_v=0.2),), SUPPLY_STEPS,
             expect=("channel:supply_v",), oracle_terms=(V_BIAS,)),
    Scenario("supply bias + scale 0.5 %/V, supply steps",
             (fx.SupplyEffect(bias_dps_per_v=0.1, scale_per_v=0.005),), SUPPLY_STEPS,
             expect=("channel:supply_v",), oracle_terms=(V_BIAS, V_SCALE)),
    Scenario("direction offset 0.05 dps, up-down sweeps",
             (fx.DirectionEffect(0.05),), DISTRACTORS, profile="up-down",
             expect=(DIRECTION,), oracle_terms=(DIR,)),
    Scenario("direction offset 0.02 dps, shuffled rates",
             (fx.DirectionEffect(0.02),), DISTRACTORS,
             expect=(DIRECTION,), oracle_terms=(DIR,)),
    Scenario("temperature steps + direction",
             (fx.TemperatureEffect(bias_dps_per_c=0.01), fx.DirectionEffect(0.04)), TEMP_STEPS,
             expect=("channel:temp_c", DIRECTION), oracle_terms=(T_BIAS, DIR)),
    Scenario("clean, shuffled rates, distractors", (), {**TEMP_STEPS}),
    Scenario("clean, up-down sweeps, distractors", (), DISTRACTORS, profile="up-down"),
    Scenario("clean, ascending sweeps", (), {"noise_ch": env.white_noise()}, profile="ascending"),
    Scenario("self-heating temperature = warm-up law (confounded)",
             (fx.TemperatureEffect(bias_dps_per_c=0.02),), {"temp_c": env.temperature_warmup()},
             confounded=("channel:temp_c", "time:warm-up"), oracle_terms=(T_BIAS,)),
    # The ramp's separable neighbour: the same drift with temperature stepping in random order.
    Scenario("linear drift 1 dps/h, chamber steps",
             (fx.DriftEffect(1.0),), TEMP_STEPS,
             expect=("time:linear-drift",), oracle_terms=(DRIFT,)),
    Scenario("monotonic temperature ramp (confounded with drift)",
             (fx.TemperatureEffect(bias_dps_per_c=0.01),), {"temp_c": env.temperature_ramp()},
             # the temperature side may be its level or its lag (on a ramp they differ only at
             # the start); the test checks temp_c is named in the confounded group
             confounded=("time:linear-drift",), oracle_terms=(T_BIAS,)),
    # Forms nobody listed (issue 9): transforms of a channel, another axis, a rate-gated effect.
    Scenario("thermal transient: bias 0.4 dps per C/s, temperature cycling",
             (fx.TemperatureRateEffect(bias_dps_per_c_per_s=0.4),), TEMP_CYCLE,
             expect=("d/dt temp_c",), oracle_terms=(T_RATE,)),
    # Self-heating: the temperature's level, its derivative and a warm-up all follow one law.
    Scenario("thermal transient while self-heating = warm-up law (confounded)",
             (fx.TemperatureRateEffect(bias_dps_per_c_per_s=4.0),),
             {"temp_c": env.temperature_warmup(noise_c=0.002)},
             confounded=("time:warm-up",), oracle_terms=(T_RATE,)),
    Scenario("lagged temperature, tau 120 s, slow chamber steps",
             (fx.LaggedTemperatureEffect(tau_s=120.0, bias_dps_per_c=0.01),), TEMP_SLOW_STEPS,
             expect=("lag(temp_c)",), oracle_terms=(T_LAG,)),
    Scenario("lagged temperature, tau 60 s, bias + scale, heating/cooling ramps",
             (fx.LaggedTemperatureEffect(tau_s=60.0, bias_dps_per_c=0.008, scale_per_c=2e-4),),
             TEMP_TRIANGLE, expect=("lag(temp_c)",), oracle_terms=(T_LAG60, T_LAG60_SCALE)),
    Scenario("temperature hysteresis 0.03 dps, heating vs cooling, steps and holds",
             (fx.TemperatureHysteresisEffect(offset_dps=0.03),), TEMP_HOLD_STEPS,
             expect=("sign d/dt temp_c",), oracle_terms=(T_HYST,)),
    Scenario("cross-axis leakage 0.4 % from raw_x, two-axis session",
             (fx.CrossAxisEffect(coupling=0.004),), TWO_AXIS,
             expect=("channel:raw_x",), oracle_terms=(X_LEAK,)),
    Scenario("temperature scale error only above 30 dps",
             (fx.HighRateTemperatureEffect(),), TEMP_STEPS,
             expect=("temp_c × (|rate| > knee)",), oracle_terms=(T_GATED,)),
    # A rate random walk is a drift of the session that records it: where a held-out plateau is
    # predicted better with a linear drift, the drift is as right as nothing (a channel never is).
    Scenario("clean, bias instability + rate random walk, 5 distractors", (), FIVE_DISTRACTORS,
             gyro=COLOURED, also_right=(("time:linear-drift",),)),
    Scenario("clean, white noise, 5 distractors", (), FIVE_DISTRACTORS),
)



def _spline_of(fn: Callable[[np.ndarray], np.ndarray], lo: float, hi: float, channel: str,
               points: int = 64, spec: TermKind = CHANNEL_SPLINE, **fields) -> Term:
    """A spline term interpolating ``fn`` closely (``points`` knots): an oracle told a form no
    other term kind writes (of the channel, or of ΔV for a rate spline)."""
    from scipy.interpolate import CubicSpline

    x = np.linspace(lo, hi, points)
    c = CubicSpline(x, fn(x)).c  # highest power first, per segment
    pieces = tuple(tuple(float(c[3 - k, i]) for k in range(4)) for i in range(points - 1))
    return _t(spec, "bias", channel=channel, knots=tuple(float(v) for v in x), pieces=pieces, **fields)


VIBRATION = {"vib_g": env.level_per_plateau(0.5, 8.0), **DISTRACTORS}
LOAD = {"load": env.level_per_plateau(0.0, 8.0), **DISTRACTORS}
_SATURATING = fx.SaturatingEffect()
_RATE_TC = fx.RateDependentTemperatureEffect()
_SENSITIVITY = GyroModel().sensitivity
FOUR_TEMPERATURES = {"temp_c": env.temperature_steps((-10.0, 10.0, 30.0, 50.0)), **DISTRACTORS}
_LAGGED_SATURATING = fx.LaggedSaturatingEffect()
_SATURATING_TRANSIENT = fx.SaturatingTransientEffect()
#: A chamber stepped through ten temperatures in random order, each held 90 s: the die follows
#: with τ = 90 s, so its temperature sweeps the range between the chamber's levels.
TEN_TEMPERATURES = {"temp_c": env.temperature_steps(tuple(np.linspace(-10.0, 50.0, 10)), period_s=90.0),
                    **DISTRACTORS}
#: Smooth effects of a channel (issue 21), scored over several seeds by the closed loop's tests:
#: a square over a wide range (on the list, as level + square) and a saturating function (on no
#: list: the smooth form must learn it). Kept apart from :data:`SCENARIOS`, whose figures the
#: effects benchmark records.
SMOOTH_SCENARIOS: tuple[Scenario, ...] = (
    Scenario("vibration rectification: bias 0.004 dps/g² over 0.5-8 g rms per plateau",
             (fx.SquareLawEffect(),), VIBRATION, expect=("channel:vib_g",),
             oracle_terms=(_t(CHANNEL_OFFSET, "bias", channel="vib_g"),
                           _t(CHANNEL_SQUARE, "bias", channel="vib_g"))),
    Scenario("bias saturating with a channel: 0.12 dps tanh((load - 4)/1.2), load 0-8 per plateau",
             (_SATURATING,), LOAD, expect=("smooth(load)",),
             oracle_terms=(_spline_of(lambda v: np.tanh((v - _SATURATING.centre) / _SATURATING.width),
                                      -1.0, 9.0, "load"),)),
    # The scale error k(ω)·(T − 25)·ΔV as the rate spline writes it: (T − 25)·R(ΔV), R = s(ΔV/S)·ΔV.
    # Its hinge neighbour, temp_c × (|rate| > knee), may come within the loop's bar of it on a draw:
    # the simpler (nested) form is then taken, alone or with the smooth form on top: as right.
    Scenario("temperature coefficient rising with rate: 2e-4/C x r²/(1+r²), r = rate/20 dps, 4 temperatures",
             (_RATE_TC,), FOUR_TEMPERATURES, expect=("smooth(temp_c × rate)",),
             also_right=(("temp_c × (|rate| > knee)",),
                         ("temp_c × (|rate| > knee)", "smooth(temp_c × rate)")),
             oracle_terms=(_spline_of(lambda dv: _RATE_TC.shape(dv / _SENSITIVITY) * dv,
                                      -1.2 * 60 * _SENSITIVITY, 1.2 * 60 * _SENSITIVITY, "temp_c",
                                      spec=CHANNEL_RATE_SPLINE, reference=_RATE_TC.reference_c),)),
    # Told: a spline through the tanh of the lag at 64 knots, its τ estimated as the loop's is.
    Scenario("bias saturating with the die's lagged temperature: 0.1 dps tanh((lag90(T) - 25)/8), 10 levels",
             (_LAGGED_SATURATING,), TEN_TEMPERATURES, expect=("smooth(lag(temp_c))",),
             oracle_terms=(_spline_of(_LAGGED_SATURATING.shape, -15.0, 55.0, "temp_c",
                                      spec=CHANNEL_LAG_SPLINE, tau_s=_LAGGED_SATURATING.tau_s),)),
    # Told: a spline through the tanh of the rate of change at 64 knots, with the true τ (3 s; the
    # loop's window is chosen from the channel's noise). The sign of the change is the tanh's
    # limit of zero width, a form of the same rate: where it takes up what the window's τ leaves,
    # the attribution is as right.
    Scenario("thermal transient saturating: 0.08 dps tanh(dT/dt / 0.1 C/s), temperature cycling",
             (_SATURATING_TRANSIENT,), TEMP_CYCLE, expect=("smooth(d/dt temp_c)",),
             also_right=(("smooth(d/dt temp_c)", "sign d/dt temp_c"),),
             oracle_terms=(_spline_of(_SATURATING_TRANSIENT.shape, -0.6, 0.6, "temp_c",
                                      spec=CHANNEL_DERIVATIVE_SPLINE, tau_s=_SATURATING_TRANSIENT.tau_s),)),
)

# A sensor whose error follows a variable nobody recorded: no candidate can represent it.
UNEXPLAINED = Scenario("bias following an unrecorded variable (unexplained)",
                       (fx.HiddenVariableEffect(),), DISTRACTORS, leaves_residual=True)
