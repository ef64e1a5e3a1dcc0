"""PNG plots of a calibration, for a calibration engineer who would rather look than read.

* residual versus table rate, before and after the closed loop (held-out plateaus);
* per accepted effect, the residual the effect explains versus its variable
  (channel value, time since power-on, or direction state), with the fitted term;
* per confounded pair, the residual against each candidate's variable.

Uses matplotlib's Agg backend: no display needed. Files are written atomically.
"""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from canical.atomic_file import make_dirs, write_bytes_atomic
from canical.blocks import Blocks
from canical.closed_loop import LoopResult, effect_contribution, predict
from canical.terms import term_from_dict


def _save(fig, path: Path) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    write_bytes_atomic(path, buf.getvalue())


def variable_of(name: str, blocks: Blocks) -> tuple[np.ndarray, str]:
    """The x-axis for a candidate: its channel, time since power-on, or direction state."""
    if name.startswith("channel:"):
        ch = name.split(":", 1)[1]
        return blocks.aux[ch], ch
    if name.startswith("time"):
        return blocks.time_s, "time since power-on (s)"
    if name == "rate-of-change":
        return blocks.slope, "rate of change of raw (counts/s)"
    return blocks.direction, "direction state (−1 falling, +1 rising)"


def residual_vs_rate(loop: LoopResult, path: Path) -> None:
    rate = loop.blocks.points.rate
    fig, ax = plt.subplots(figsize=(8, 4.2))
    ax.plot(
        rate,
        loop.errors_before,
        ".",
        ms=3,
        alpha=0.6,
        label=f"rate model only: rms {loop.rms_before:.4f} deg/s",
    )
    ax.plot(
        rate, loop.errors_after, ".", ms=3, alpha=0.8, label=f"with effects: rms {loop.rms_after:.4f} deg/s"
    )
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("table rate (deg/s)")
    ax.set_ylabel("held-out error (deg/s)")
    ax.set_title("Error on held-out plateaus, before and after closing the loop")
    ax.legend(loc="best", fontsize=8)
    _save(fig, path)


def effect_plot(loop: LoopResult, effect: dict, path: Path) -> None:
    """Partial residual: the final model's residual plus this effect's own contribution."""
    blocks = loop.blocks
    resid = blocks.points.rate - predict(loop.fit, blocks)
    terms = tuple(term_from_dict(t) for t in effect["terms"])
    contribution = effect_contribution(loop.fit, blocks, terms)
    x, label = variable_of(effect["name"], blocks)
    # The correction subtracts the error, so the sensor's error is the negative contribution.
    fig, ax = plt.subplots(figsize=(8, 4.2))
    ax.plot(x, -(resid + contribution), ".", ms=3, alpha=0.6, label="sensor error explained (blocks)")
    ax.plot(x, -contribution, "x", ms=3, alpha=0.8, label="fitted terms (scale-factor terms vary with rate)")
    ax.set_xlabel(label)
    ax.set_ylabel("rate error (deg/s)")
    ax.set_title(
        f"Effect {effect['name']}: when added, held-out rms {effect['rms_before_dps']:.4f} -> "
        f"{effect['rms_after_dps']:.4f} deg/s"
    )
    ax.legend(loc="best", fontsize=8)
    _save(fig, path)


def confounded_plot(loop: LoopResult, group: dict, path: Path) -> None:
    blocks = loop.blocks
    resid = blocks.points.rate - loop.base_fit.poly.evaluate(blocks.points.dv)[0]
    names = group["candidates"][:2]
    fig, axes = plt.subplots(1, len(names), figsize=(9, 3.8), squeeze=False)
    for ax, name in zip(axes[0], names, strict=True):
        x, label = variable_of(name, blocks)
        ax.plot(x, resid, ".", ms=3, alpha=0.6)
        ax.set_xlabel(label)
        ax.set_ylabel("residual of the rate model (deg/s)")
        ax.set_title(name, fontsize=9)
    fig.suptitle("Confounded: both explain the same residual", fontsize=10)
    _save(fig, path)


def write_plots(loop: LoopResult, directory: Path) -> list[Path]:
    """All plots of a loop result into ``directory``; returns the paths written."""
    make_dirs(directory)
    written = [directory / "residual_vs_rate.png"]
    residual_vs_rate(loop, written[0])
    for i, effect in enumerate(loop.effects, 1):
        path = directory / f"effect_{i}_{effect['name'].replace(':', '_')}.png"
        effect_plot(loop, effect, path)
        written.append(path)
    for i, group in enumerate(loop.confounded, 1):
        path = directory / f"confounded_{i}.png"
        confounded_plot(loop, group, path)
        written.append(path)
    return written
