"""PNG plots of a calibration, for a calibration engineer who would rather look than read.

* residual versus table rate, before and after the closed loop (held-out plateaus);
* per accepted effect, the residual the effect explains versus its variable
  (channel value, time since power-on, or direction state), with the fitted term; a
  channel's coefficient that changes with rate, versus the table rate, coloured by the channel;
* per confounded pair, the residual against each candidate's variable;
* what stays unexplained: the held-out residual after the loop against time and
  against every candidate variable (each channel's level, derivative, lag,
  direction of change...), the best-correlated first.

Uses matplotlib's Agg backend: no display needed. Files are written atomically.
"""

from __future__ import annotations

import io
import re
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from canical.closed_loop.blocks import Blocks
from canical.closed_loop.candidates import DIRECTION_NAME, SLOPE_NAME, WARMUP_NAME, retimed
from canical.closed_loop.findings import Confound, Effect
from canical.closed_loop.search import LoopResult, effect_contribution, predict
from canical.closed_loop.unexplained import account, candidate_variables, correlations
from canical.files.atomic_file import make_dirs, write_bytes_atomic
from canical.sets.term_kinds import CHANNEL_LAG, CHANNEL_OFFSET, CHANNEL_RATE_SPLINE, TIME
from canical.sets.term_params import Tau


def _save(fig, path: Path) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    write_bytes_atomic(path, buf.getvalue())


#: Units of auxiliary channels by the suffix of their name (a set names channels, not units).
SUFFIX_UNITS = {"c": "°C", "degc": "°C", "k": "K", "v": "V", "mv": "mV", "a": "A", "ma": "mA", "g": "g",
                "dps": "deg/s", "s": "s", "hz": "Hz", "pa": "Pa", "pct": "%"}
#: How a channel's level candidate is named (``channel:temp_c``): what follows is the channel.
LEVEL_PREFIX = CHANNEL_OFFSET.label("")


def held_out(blocks: Blocks) -> str:
    """What every plot of the loop measures its errors on."""
    return f"held out: whole plateaus ({blocks.label}), each predicted by a fit without it"


def channel_unit(channel: str) -> str:
    """A channel's unit from its name's suffix (``temp_c`` °C, ``supply_v`` V, ``accel_g`` g);
    ``raw...`` channels are the sensor's raw units; unknown: ``units of <channel>``."""
    if channel.startswith("raw"):
        return "raw units"
    suffix = channel.rsplit("_", 1)[-1].lower() if "_" in channel else ""
    return SUFFIX_UNITS.get(suffix, f"units of {channel}")


def variable_label(name: str) -> str:
    """An axis label with its unit for a candidate's variable (``d/dt temp_c`` -> °C/s)."""
    if name == "time since power-on":
        return "time since power-on (s)"
    if name.startswith("sign d/dt "):
        return f"{name} (−1 falling, +1 rising)"
    if name.startswith("d/dt "):
        return f"{name} ({channel_unit(name[5:])}/s)"
    lag = re.match(r"lag\(([^,)]+)", name)
    if lag:
        return f"{name} ({channel_unit(lag.group(1))})"
    gated = re.match(r"(\S+) × \(\|rate\|", name)
    if gated:
        return f"{name} ({channel_unit(gated.group(1))})"
    if name.startswith(LEVEL_PREFIX):
        channel = name.removeprefix(LEVEL_PREFIX)
        return f"{channel} ({channel_unit(channel)})"
    smooth = re.fullmatch(r"smooth\((.+?)(?: × rate)?\)", name)
    if smooth and smooth.group(1).startswith(("lag(", "d/dt ")):  # of a transform: drawn against it
        return variable_label(smooth.group(1))
    if smooth:  # a learned function of the channel: drawn against the channel itself
        return f"{smooth.group(1)} ({channel_unit(smooth.group(1))})"
    if name.startswith(WARMUP_NAME):
        return f"{name}: 1 − exp(−t/τ) (no unit)"
    if name.startswith(TIME):
        return f"{name}: time since power-on (s)"
    if name == SLOPE_NAME:
        return "rate of change of raw (raw units/s)"
    if name == DIRECTION_NAME:
        return "direction state (−1 falling, +1 rising)"
    return name


def variable_of(name: str, blocks: Blocks, loop: LoopResult | None = None) -> tuple[np.ndarray, str]:
    """The x-axis for a candidate: its channel (or its transform), time since power-on, or direction."""
    cand = next((c for c in (loop.candidates if loop else []) if c.name == name), None)
    if cand is not None and not name.startswith((LEVEL_PREFIX, TIME, DIRECTION_NAME, SLOPE_NAME)):
        # a smooth form of a lag is drawn against the lag with the τ the fit found, not the start's
        fitted = next((t.params for t in (loop.fit.terms if loop else ()) if t.spec is cand.terms[0].spec
                       and t.channel == cand.channel and isinstance(t.params, Tau)), None)
        if fitted is not None:
            cand = cand.with_terms(tuple(retimed(t, fitted.tau_s) for t in cand.terms))
        return candidate_variables([cand], blocks)[name], variable_label(name)
    if name.startswith(LEVEL_PREFIX):
        return blocks.aux[name.removeprefix(LEVEL_PREFIX)], variable_label(name)
    if name.startswith(TIME):
        return blocks.time_s, "time since power-on (s)"
    if name == SLOPE_NAME:
        return blocks.slope, variable_label(name)
    return blocks.direction, variable_label(DIRECTION_NAME)


def residual_vs_rate(loop: LoopResult, path: Path) -> None:
    """Before and after, each on its own scale: the error after is often a hundredth of before's."""
    rate = loop.blocks.points.rate
    fig, axes = plt.subplots(2, 1, figsize=(8, 6.2), sharex=True)
    panels = (
        (axes[0], loop.errors_before, loop.rms_before, "rate model alone", "C0"),
        (axes[1], loop.errors_after, loop.rms_after, "written set (rate model and effect terms)", "C1"),
    )
    for ax, errors, rms, what, colour in panels:
        ax.plot(rate, errors, ".", ms=3, alpha=0.7, color=colour)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylabel("error (deg/s)")
        ax.set_title(f"{what}: held-out rms {rms:.4f} deg/s", fontsize=10)
        ax.grid(True, alpha=0.3)
    axes[1].set_xlabel("table rate (deg/s)")
    fig.suptitle(f"Error on held-out plateaus, before and after closing the loop\n({held_out(loop.blocks)})",
                 fontsize=10)
    fig.tight_layout()
    _save(fig, path)


def effect_plot(loop: LoopResult, effect: Effect, path: Path) -> None:
    """Partial residual: the final model's residual plus this effect's own contribution."""
    blocks = loop.blocks
    resid = blocks.points.rate - predict(loop.fit, blocks)
    terms = effect.terms
    contribution = effect_contribution(loop.fit, blocks, terms)
    x, label = variable_of(effect.name, blocks, loop)
    by_rate = any(t.spec is CHANNEL_RATE_SPLINE for t in terms)
    # The correction subtracts the error, so the sensor's error is the negative contribution.
    fig, ax = plt.subplots(figsize=(8, 4.2))
    if by_rate:  # a channel's coefficient changing with rate: along the rate, coloured by the channel
        dots = ax.scatter(blocks.points.rate, -(resid + contribution), c=x, s=6, alpha=0.7,
                          label="sensor error explained (blocks)")
        fig.colorbar(dots, ax=ax, label=label)
        x, label = blocks.points.rate, "table rate (deg/s)"
    else:
        ax.plot(x, -(resid + contribution), ".", ms=3, alpha=0.6, label="sensor error explained (blocks)")
    ax.plot(x, -contribution, "x", ms=3, alpha=0.8, color="k" if by_rate else None,
            label="fitted terms (scale-factor terms vary with rate)")
    ax.set_xlabel(label)
    ax.set_ylabel("rate error (deg/s)")
    ax.set_title(
        f"Effect {effect.name}: when added, held-out rms {effect.rms_before_dps:.4f} -> "
        f"{effect.rms_after_dps:.4f} deg/s\n(points: every block, final fit; rms: {held_out(blocks)})",
        fontsize=10,
    )
    ax.legend(loc="best", fontsize=8)
    _save(fig, path)


def confounded_plot(loop: LoopResult, group: Confound, path: Path) -> None:
    blocks = loop.blocks
    resid = blocks.points.rate - loop.base_fit.poly.evaluate(blocks.points.dv)[0]
    names = group.candidates[:2]
    fig, axes = plt.subplots(1, len(names), figsize=(9, 3.8), squeeze=False)
    for ax, name in zip(axes[0], names, strict=True):
        x, label = variable_of(name, blocks, loop)
        ax.plot(x, resid, ".", ms=3, alpha=0.6)
        ax.set_xlabel(label)
        ax.set_ylabel("residual of the rate model (deg/s)")
        ax.set_title(name, fontsize=9)
    fig.suptitle("Confounded: both explain the same residual of the rate model (all blocks, in-sample)",
                 fontsize=10)
    _save(fig, path)


def _in_label_units(loop: LoopResult) -> dict[str, float]:
    """Per candidate whose feature is its channel (or the channel's lag) less a reference, that
    reference: added back, the panel draws the channel in the unit its label names (a
    temperature of −10…50 °C, not the −40…22 of the feature)."""
    return {c.name: c.terms[0].reference for c in loop.candidates
            if c.terms[0].spec in (CHANNEL_OFFSET, CHANNEL_LAG)}


def unexplained_plot(loop: LoopResult, path: Path) -> None:
    """The residual after the loop against time and every candidate variable, best-correlated first."""
    _save(unexplained_figure(loop), path)


def unexplained_figure(loop: LoopResult):
    """:func:`unexplained_plot`'s figure. Laid out by matplotlib's constrained layout: it places
    the figure's title above the panels' titles (``tight_layout`` ignores a suptitle, and the
    title was drawn over the first row's)."""
    blocks = loop.blocks
    resid = loop.errors_after
    variables = candidate_variables(loop.candidates, blocks)
    ranked = correlations(resid, variables)
    order = ["time since power-on", *(n for n, _ in ranked if n != "time since power-on")]
    r_of = dict(ranked)
    shift = _in_label_units(loop)
    cols = 4
    rows = (len(order) + cols - 1) // cols
    fig, axes = plt.subplots(rows, cols, figsize=(3.2 * cols, 2.6 * rows), squeeze=False,
                             layout="constrained")
    for ax, name in zip(axes.flat, order, strict=False):
        ax.plot(variables[name] + shift.get(name, 0.0), resid, ".", ms=2, alpha=0.6)
        ax.axhline(0, color="k", lw=0.5)
        ax.set_title(f"{name}  |r| {r_of[name]:.2f}", fontsize=8)
        ax.set_xlabel(variable_label(name), fontsize=7)
        ax.set_ylabel("residual (deg/s)", fontsize=7)
        ax.tick_params(labelsize=7)
    for ax in list(axes.flat)[len(order):]:
        ax.axis("off")
    left = account(resid, blocks.points.rate - predict(loop.fit, blocks), blocks, loop.candidates)
    verdict = "UNEXPLAINED" if left.unexplained else "explained"
    fig.suptitle(
        f"Held-out residual after the loop: {left.held_out_robust_rms_dps:.4f} deg/s rms (robust), "
        f"{left.ratio:.1f}x the noise floor {left.noise_floor_dps:.4f} deg/s ({verdict})\n"
        f"({held_out(blocks)})",
        fontsize=10,
    )
    return fig


def _file_name(name: str) -> str:
    """A candidate name as a file name part: d/dt temp_c -> d_dt_temp_c."""
    return re.sub(r"[^A-Za-z0-9_.-]+", "_", name).strip("_")


def write_plots(loop: LoopResult, directory: Path) -> list[Path]:
    """All plots of a loop result into ``directory``; returns the paths written."""
    make_dirs(directory)
    written = [directory / "residual_vs_rate.png"]
    residual_vs_rate(loop, written[0])
    for i, effect in enumerate(loop.effects, 1):
        path = directory / f"effect_{i}_{_file_name(effect.name)}.png"
        effect_plot(loop, effect, path)
        written.append(path)
    for i, group in enumerate(loop.confounded, 1):
        path = directory / f"confounded_{i}.png"
        confounded_plot(loop, group, path)
        written.append(path)
    path = directory / "unexplained_residual.png"
    unexplained_plot(loop, path)
    written.append(path)
    return written
