"""Blind cases for the closed loop: effects, channel trajectories and drifts drawn at random.

The project's scenarios (:mod:`canical.sim.scenarios`) are few and were looked at while the loop was
shaped; a loop can score on them and still blame a drift on a channel or leave a confounded effect
uncorrected on a session it never saw. :func:`draw_case` draws one session's story from a seed:

* an effect form — none (a clean sensor), a channel's level, its rate of change (a thermal
  transient), its lag, a warm-up after power-on, or a form no candidate lists (a bias saturating
  with the channel, tanh of its level; a bias following the channel's level cubed);
* the channel's trajectory — cycling, heating/cooling ramps, steps in random order, a level per
  plateau, or noise only (so the effect, if any, cannot be seen);
* a drift of the sensor no channel explains — none, a bias random walk, flicker (bias instability),
  or bias steps at random times.

Each case says what a right answer is: the channel an effect must be blamed on (any of its forms),
or that no channel may be blamed (a clean sensor, or a trajectory that hides the effect). Seeds
0-99 are for development; a benchmark draws its blind seeds from a seed it never prints.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field

import numpy as np

from canical.sets.term_kinds import CHANNEL_DERIVATIVE, CHANNEL_LAG, CHANNEL_OFFSET, TIME_WARMUP
from canical.sets.terms import Term
from canical.sim import effects as fx
from canical.sim import environment as env
from canical.sim.gyro import GyroModel
from canical.sim.scenarios import DISTRACTORS, Scenario

CHANNEL = "temp_c"
FORMS = ("none", "level", "transient", "lag", "warm-up", "saturating", "cubic")
TRAJECTORIES = ("cycling", "ramps", "steps", "per-plateau", "noise")
DRIFTS = ("none", "random-walk", "flicker", "steps")


@dataclass(frozen=True)
class BiasSteps:
    """Bias stepping at random times (a sensor's bias jumping: a shock, a mode change)."""

    times_s: tuple[float, ...]
    sizes_dps: tuple[float, ...]

    def errors(self, time_s, rate_dps, aux):
        t = np.asarray(time_s, dtype=float)
        bias = sum((s * (t >= at) for at, s in zip(self.times_s, self.sizes_dps, strict=True)),
                   np.zeros_like(t))
        return bias, 0.0


@dataclass(frozen=True)
class CubicTemperatureEffect:
    """Bias following the cube of the temperature's offset: a form no candidate lists."""

    channel: str = CHANNEL
    reference_c: float = 25.0
    dps_per_c3: float = 1e-5

    def errors(self, time_s, rate_dps, aux):
        return self.dps_per_c3 * (np.asarray(aux[self.channel]) - self.reference_c) ** 3, 0.0


@dataclass(frozen=True)
class BlindCase:
    """One drawn case: the scenario to calibrate and what a right answer is."""

    seed: int
    form: str
    trajectory: str
    drift: str
    scenario: Scenario
    # The channel an effect must be blamed on (any of its forms), None: none may be.
    blame: str | None
    time_effect: bool = False  # a warm-up: a time candidate must take it
    notes: dict[str, float] = field(default_factory=dict)

    @property
    def describe(self) -> str:
        return f"{self.form} / {self.trajectory} / drift {self.drift}"


@dataclass(frozen=True)
class BlindClass:
    """A class of cases a criterion of the closed loop is judged on, drawn by :func:`draw_case`."""

    name: str
    forms: tuple[str, ...] = FORMS
    trajectories: tuple[str, ...] = TRAJECTORIES
    drifts: tuple[str, ...] = DRIFTS


#: Every case; a drifting sensor with no channel effect (no channel may be blamed); a real effect
#: of a form the loop lists, on a channel that shows it (it must be attributed, within 2x of a
#: model told the form).
ANY = BlindClass("any case")
DRIFT_ONLY = BlindClass("drift, no channel effect", forms=("none",),
                        drifts=("random-walk", "flicker", "steps"))
LISTED_EFFECT = BlindClass("listed effect", forms=("level", "transient", "lag"),
                           trajectories=("cycling", "ramps", "steps"))


def _trajectory(kind: str, rng: np.random.Generator) -> Callable:
    if kind == "cycling":
        return env.temperature_cycle(25.0, float(rng.uniform(6.0, 12.0)),
                                     (float(rng.uniform(250, 600)), float(rng.uniform(120, 240))), 0.002)
    if kind == "ramps":
        return env.temperature_triangle(15.0, 40.0, tuple(float(x) for x in rng.uniform(120, 280, 4)), 0.02)
    if kind == "steps":
        levels = tuple(float(x) for x in rng.uniform(-10.0, 50.0, 5))
        return env.temperature_steps(levels, float(rng.uniform(60, 150)), 0.05, int(rng.integers(1 << 30)),
                                     float(rng.uniform(5, 30)))
    if kind == "per-plateau":
        return env.level_per_plateau(10.0, 40.0, 0.02)
    return env.white_noise(25.0, 0.05)


def _effect(form: str, rng: np.random.Generator) -> tuple[tuple, tuple[Term, ...]]:
    """The effect and the term forms of a model told the truth (empty where no term writes it)."""
    sign = float(rng.choice([-1.0, 1.0]))
    if form == "level":
        return ((fx.TemperatureEffect(bias_dps_per_c=sign * float(rng.uniform(0.004, 0.02))),),
                (Term.of(CHANNEL_OFFSET, "bias", 0.0, channel=CHANNEL, reference=25.0),))
    if form == "transient":
        return ((fx.TemperatureRateEffect(bias_dps_per_c_per_s=sign * float(rng.uniform(0.2, 1.0))),),
                (Term.of(CHANNEL_DERIVATIVE, "bias", 0.0, channel=CHANNEL, tau_s=3.0),))
    if form == "lag":
        tau = float(rng.uniform(40.0, 150.0))
        bias = sign * float(rng.uniform(0.005, 0.02))
        return ((fx.LaggedTemperatureEffect(tau_s=tau, bias_dps_per_c=bias),),
                (Term.of(CHANNEL_LAG, "bias", 0.0, channel=CHANNEL, tau_s=tau),))
    if form == "warm-up":
        tau = float(rng.uniform(100.0, 300.0))
        return ((fx.WarmupEffect(sign * float(rng.uniform(0.08, 0.3)), tau),),
                (Term.of(TIME_WARMUP, "bias", 0.0, tau_s=tau),))
    if form == "saturating":
        return ((fx.SaturatingEffect(channel=CHANNEL, amplitude_dps=sign * float(rng.uniform(0.05, 0.15)),
                                     centre=25.0, width=float(rng.uniform(4.0, 10.0))),), ())
    if form == "cubic":
        return ((CubicTemperatureEffect(dps_per_c3=sign * float(rng.uniform(2e-5, 1e-4))),), ())
    return (), ()


def _drift(kind: str, rng: np.random.Generator) -> tuple[GyroModel, tuple]:
    """The sensor's own drift: in its noise model, or as bias steps."""
    if kind == "random-walk":  # 0.05-0.15 deg/s over a 10-minute session
        return GyroModel(rate_random_walk_dps_rt_s=float(rng.uniform(0.05, 0.15)) / np.sqrt(600.0)), ()
    if kind == "flicker":
        return GyroModel(bias_instability_dps=float(rng.uniform(0.002, 0.01))), ()
    if kind == "steps":
        n = int(rng.integers(1, 4))
        return GyroModel(), (BiasSteps(tuple(float(x) for x in rng.uniform(60, 600, n)),
                                       tuple(float(x) for x in rng.normal(0.0, 0.05, n))),)
    return GyroModel(), ()


def draw_case(seed: int, within: BlindClass = ANY) -> BlindCase:
    """One case from ``seed``: form, trajectory and drift drawn independently, then their parameters.

    A narrower class (a drifting sensor with no channel effect, say) lets a criterion on that class
    be scored on as many seeds as it needs."""
    rng = np.random.default_rng([seed, 32])
    form = str(rng.choice(within.forms))
    trajectory = str(rng.choice(within.trajectories))
    drift = str(rng.choice(within.drifts))
    effects, told = _effect(form, rng)
    gyro, drift_effects = _drift(drift, rng)
    channel_form = form not in ("none", "warm-up")
    # Noise only hides any effect of the channel; a level per plateau jumps between plateaus (no
    # thermal lag), so its rate of change is nil on every plateau and hides a transient.
    hidden = trajectory == "noise" or (form == "transient" and trajectory == "per-plateau")
    visible = channel_form and not hidden
    scenario = Scenario(f"blind {seed}", (*effects, *drift_effects),
                        {CHANNEL: _trajectory(trajectory, rng), **DISTRACTORS},
                        gyro=gyro, oracle_terms=told)
    return BlindCase(seed, form, trajectory, drift, scenario, CHANNEL if visible else None,
                     time_effect=form == "warm-up")
