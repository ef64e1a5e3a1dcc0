"""The report of a drive replayed with bias tracking: what was learned, where, and what it changed.

Why: a bias learned on the vehicle changes every rate the vehicle's software sees, so a user
must be able to check it: the heading with and without tracking, the learned bias against
temperature (the effect the table set lacked), and every standstill used or refused and why.
Writes ``drive.md``, ``standstills.csv`` and two PNG plots, all atomically.
"""

from __future__ import annotations

import io
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from canical.files.atomic_file import make_dirs, write_bytes_atomic, write_text_atomic
from canical.tracking.explain import OFFSETS, chosen, explain, too_little_evidence
from canical.tracking.replay import Replay

#: Said wherever a temperature would be shown, when the drive had none (the tracker then states
#: the bias at its reference temperature, which nobody measured).
NO_TEMPERATURE = "not recorded"


def _save(fig, path: Path) -> None:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    write_bytes_atomic(path, buf.getvalue())


def heading_deg(time_s: np.ndarray, rate_dps: np.ndarray) -> np.ndarray:
    """Integrated rate (deg), a step per row; a power-on (time going back) adds nothing."""
    dt = np.diff(time_s, prepend=time_s[0])
    dt[dt < 0] = 0.0
    return np.cumsum(np.nan_to_num(rate_dps) * dt)


def still_drift(time_s: np.ndarray, rate_dps: np.ndarray, out: Replay, axis: int) -> tuple[float, float]:
    """Heading drift over the windows learned from (the vehicle stood: any turning is error)."""
    dt = np.diff(time_s, prepend=time_s[0])
    dt[dt < 0] = 0.0
    cycle = np.cumsum(np.r_[0, np.diff(time_s) < 0])
    before = after = 0.0
    for w in out.taken:
        rows = (cycle == w.power_cycle) & (time_s >= w.start_s) & (time_s <= w.end_s)
        before += float(np.sum(rate_dps[rows] * dt[rows]))
        after += float(np.sum((rate_dps[rows] - out.bias_dps[rows, axis]) * dt[rows]))
    return before, after


def write_drive_report(directory: str | Path, time_s: np.ndarray, rate_dps: np.ndarray, out: Replay,
                       axes: tuple[str, ...]) -> list[Path]:
    """drive.md, standstills.csv, heading.png and bias_vs_temperature.png (bias_vs_time.png when
    the drive recorded no temperature) in ``directory``."""
    folder = Path(directory)
    make_dirs(folder)
    rates = np.asarray(rate_dps, dtype=float).reshape(len(time_s), -1)
    lines = ["# Drive replayed with bias tracking", "",
             f"{len(time_s)} rows, {out.power_cycles} power-on(s), {len(out.events)} standstill(s): "
             f"{sum(e.decision == 'adopted' for e in out.events)} used, "
             f"{sum(e.decision == 'refused' for e in out.events)} refused; "
             f"{len(out.taken)} windows learned from.", "",
             "| axis | integrated rate without tracking (deg) | with (deg) "
             "| drift at standstills without (deg) | with (deg) | learned slope (deg/s/°C) | updates |",
             "|---|---|---|---|---|---|---|"]
    fig, ax = plt.subplots(figsize=(8, 4))
    for a, name in enumerate(axes):
        raw_heading = heading_deg(time_s, rates[:, a])
        tracked = heading_deg(time_s, rates[:, a] - out.bias_dps[:, a])
        drift = still_drift(time_s, rates[:, a], out, a)
        state = out.learned[a]
        slope = f"{state.slope:+.5f}" if out.temperature_recorded else f"- (temperature {NO_TEMPERATURE})"
        lines.append(f"| {name} | {raw_heading[-1]:.2f} | {tracked[-1]:.2f} | {drift[0]:.3f} "
                     f"| {drift[1]:.3f} | {slope} | {state.updates} |")
        on_time = heading_deg(time_s, np.ones(len(time_s)))
        ax.plot(on_time, raw_heading, label=f"{name} without tracking")
        ax.plot(on_time, tracked, label=f"{name} with tracking")
    ax.set_xlabel("time switched on, all power-ons in order (s)")
    ax.set_ylabel("integrated rate (deg)")
    ax.set_title("Heading: the integrated rate with and without the learned bias")
    ax.legend()
    bias_plot = "bias_vs_temperature.png" if out.temperature_recorded else "bias_vs_time.png"
    paths = [folder / "heading.png", folder / bias_plot, folder / "standstills.csv", folder / "drive.md"]
    _save(fig, paths[0])
    _save(_bias_figure(out, axes), paths[1])
    csv = ["start_s,end_s,power_on,decision,windows_used,windows_refused,temp_c,"
           + ",".join(f"mean_{n}_dps,sigma_{n}_dps" for n in axes) + ",reason"]
    for a, name in enumerate(axes):
        lines += _follows(out, a, name)
    lines += ["", "## Standstills", "", "| power-on | from (s) | to (s) | °C | decision | why |",
              "|---|---|---|---|---|---|"]
    for e in out.events:
        cells = ",".join(f"{m:.6f},{u:.6f}" for m, u in zip(e.mean_dps, e.uncertainty_dps, strict=True))
        temp = f"{e.temp_c:.2f}" if out.temperature_recorded else ""
        csv.append(f"{e.start_s:.3f},{e.end_s:.3f},{e.power_cycle},{e.decision},{e.windows_used},"
                   f"{e.windows_refused},{temp},{cells},\"{e.reason}\"")
        shown = f"{e.temp_c:.1f}" if out.temperature_recorded else NO_TEMPERATURE
        lines.append(f"| {e.power_cycle} | {e.start_s:.1f} | {e.end_s:.1f} | {shown} | {e.decision} "
                     f"| {e.reason} |")
    what = "temperature" if out.temperature_recorded else "time since power-on"
    lines += ["", "![heading](heading.png)", "", f"![bias against {what}]({bias_plot})", ""]
    write_text_atomic(paths[2], "\n".join(csv) + "\n")
    write_text_atomic(paths[3], "\n".join(lines))
    return paths


def _bias_figure(out: Replay, axes: tuple[str, ...]):
    """The window means learned from and the learned bias, against temperature; against time
    since power-on when the drive had no temperature (the reference's 25 °C is no reading)."""
    fig, ax = plt.subplots(figsize=(8, 4))
    recorded = out.temperature_recorded
    for a, name in enumerate(axes):
        for cycle in range(out.power_cycles):
            taken = [w for w in out.taken if w.power_cycle == cycle]
            if not taken:
                continue
            x = [w.temp_c if recorded else 0.5 * (w.start_s + w.end_s) for w in taken]
            dots = ax.plot(x, [w.mean_dps[a] for w in taken], ".", alpha=0.4,
                           label=f"{name}, power-on {cycle}: window means")
            ax.plot(x, [w.after_dps[a] for w in taken], "-",
                    color=dots[0].get_color(), label=f"{name}, power-on {cycle}: learned")
    ax.set_xlabel("temperature (°C)" if recorded else "time since power-on (s)")
    ax.set_ylabel("bias (deg/s)")
    ax.set_title("Learned bias against temperature" if recorded
                 else f"Learned bias against time since power-on (temperature {NO_TEMPERATURE})")
    if ax.get_legend_handles_labels()[0]:
        ax.legend(fontsize="small")
    return fig


def _follows(out: Replay, a: int, name: str) -> list[str]:
    """The section on what the bias on one axis follows: the models fitted to the windows, or
    why the windows are too little evidence to tell."""
    if not out.taken:
        return []
    head = ["", f"## What the bias on {name} follows", ""]
    short = too_little_evidence(out.taken)
    if short is not None:
        return [*head, f"Too little evidence to tell: {short}."]
    models = explain(out.taken, a)
    if not models:  # as many power-ons as windows: nothing is left to fit a term to
        return [*head, "Too little evidence to tell: no power-on has windows enough for a term."]
    pick = chosen(models)
    before = next(m.rms_dps for m in models if m.model == OFFSETS)
    found = (f"**{pick.model}**: no term earns its place beyond the offsets" if pick.model == OFFSETS
             else f"**{pick.model}**, the effect the set lacks; rms {before:.4f} deg/s with offsets "
                  f"alone, {pick.rms_dps:.4f} with it")
    without = "" if out.temperature_recorded else f" (temperature {NO_TEMPERATURE}: no temperature term)"
    return [*head, "The window means learned from, fitted with an offset per power-on and the terms below "
            f"(best first){without}. The simplest within 10 % of the best: {found}.", "",
            "| model | rms left (deg/s) | terms |", "|---|---|---|",
            *(f"| {m.model} | {m.rms_dps:.4f} | "
              f"{', '.join(f'{k} {v:+.3g}' for k, v in m.terms.items()) or '-'} |" for m in models)]
