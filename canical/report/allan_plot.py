"""The Allan deviation plot: log-log σ(τ) with its error bars and the lines the terms were read from.

Drawn from the analysis record (:class:`canical.calibrate.allan.NoiseAnalysis`), so that the calibrate
report and ``canical noise`` plot the same thing from the same data. Written atomically.
"""

from __future__ import annotations

import io
from pathlib import Path
from typing import TYPE_CHECKING

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from canical.files.atomic_file import write_bytes_atomic

if TYPE_CHECKING:
    from canical.calibrate.allan import NoiseAnalysis

SQRT_HOUR = 60.0


def term_lines(analysis: NoiseAnalysis, tau: np.ndarray) -> dict[str, np.ndarray]:
    """σ(τ) in deg/s of each resolved term's line, from its read-out in report units."""
    terms = analysis.terms
    lines: dict[str, np.ndarray] = {}
    if terms.arw.resolved:
        n = terms.arw.value / SQRT_HOUR
        lines[f"ARW {terms.arw.value:.3g} deg/√h"] = n / np.sqrt(tau)
    if terms.bias_instability.resolved:
        b = terms.bias_instability.value / 3600.0
        lines[f"BI {terms.bias_instability.value:.3g} deg/h"] = np.full_like(tau, 0.664 * b)
    if terms.rrw.resolved:
        k = terms.rrw.value / (3600.0 * SQRT_HOUR)
        lines[f"RRW {terms.rrw.value:.3g} deg/h/√h"] = k * np.sqrt(tau / 3.0)
    return lines


def write_allan_plot(analysis: NoiseAnalysis, path: str | Path, title: str = "Allan deviation") -> Path:
    """One PNG: the pooled curve (±1 error of each point) and the resolved terms' lines."""
    curve = analysis.curve
    tau = np.asarray(curve.tau_s)
    adev = np.asarray(curve.adev)
    rel = 1.0 / np.sqrt(2.0 * np.maximum(np.asarray(curve.clusters) - 1, 1))
    fig, ax = plt.subplots(figsize=(7, 4.8))
    ax.errorbar(tau, adev, yerr=[adev * rel, adev * rel], fmt="o-", ms=3, lw=1, capsize=2,
                color="black", label="overlapping ADEV (±1/√(2(K−1)))")
    for (label, line), style in zip(term_lines(analysis, tau).items(), ("--", ":", "-."), strict=False):
        ax.plot(tau, line, style, lw=1.5, label=label)
    unresolved = [t.name for _, t in analysis.terms.items() if not t.resolved]
    if unresolved:
        ax.text(0.02, 0.02, "not resolved: " + ", ".join(unresolved), transform=ax.transAxes, fontsize=8)
    ax.set_xscale("log")
    ax.set_yscale("log")
    ax.set_xlabel("τ (s)")
    ax.set_ylabel("σ(τ) (deg/s)")
    lo, hi = analysis.tau_range_s
    ax.set_title(f"{title}: {curve.records} record(s), {curve.duration_s:.0f} s, "
                 f"τ {lo:.3g}–{hi:.3g} s", fontsize=10)
    ax.grid(True, which="both", alpha=0.3)
    ax.legend(fontsize=8)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    out = Path(path)
    write_bytes_atomic(out, buf.getvalue())
    return out
