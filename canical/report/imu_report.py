"""The report of a triad calibration: the coupling as a table and a heatmap, the errors per axis.

Works on the report's record (:class:`canical.calibration.imu_calibration_report.ImuReport`, whose
``to_dict`` is ``report.json``): the markdown page and one figure,
``coupling.png``: left, the coupling matrix as an annotated heatmap (each off-diagonal term in %
and mrad, ± its standard error); right, per axis, the held-out plateau error before and after
the coupling, as bars (single-axis sessions pooled, and the multi-axis motion when there is one).
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
    from canical.calibration.imu_calibration_report import ImuReport

AXES = ("x", "y", "z")
FIGURE = "coupling.png"


def pooled_errors(report: ImuReport, multi: bool) -> tuple[np.ndarray, np.ndarray] | None:
    """Per axis, rms before and after over the single-axis sessions' plateaus (or the multi-axis ones)."""
    rows = [e for e in report.held_out if (e.axis == "multi") == multi]
    if not rows:
        return None
    n = np.array([e.plateaus for e in rows], dtype=float)
    before = np.array([[v**2 for v in e.before_rms_dps] for e in rows])
    after = np.array([[v**2 for v in e.after_rms_dps] for e in rows])
    return np.sqrt(n @ before / n.sum()), np.sqrt(n @ after / n.sum())


def write_coupling_plot(report: ImuReport, path: Path) -> Path:
    """The heatmap and the before/after bars, as one PNG."""
    m = np.asarray(report.matrix)
    se = np.asarray(report.standard_errors)
    fig, (left, right) = plt.subplots(1, 2, figsize=(13, 4.6),
                                      gridspec_kw={"width_ratios": [1, 1.2], "wspace": 0.5})
    off = 100.0 * (m - np.diag(np.diag(m)))
    limit = max(float(np.abs(off).max()), 0.1)
    image = left.imshow(off, cmap="RdBu_r", vmin=-limit, vmax=limit)
    for i in range(3):
        for j in range(3):
            text = (f"{m[i, j]:.5f}\n±{se[i, j]:.1e}" if i == j else
                    f"{100 * m[i, j]:+.3f} %\n{1000 * np.arctan(m[i, j]):+.2f} mrad\n±{100 * se[i, j]:.3f} %")
            dark = abs(off[i, j]) > 0.6 * limit
            left.text(j, i, text, ha="center", va="center", fontsize=8, color="white" if dark else "black")
    left.set_xticks(range(3), [f"from {a}" for a in AXES])
    left.set_yticks(range(3), [f"corrected {a}" for a in AXES])
    left.set_title("coupling M (corrected = M @ per-axis rates)")
    fig.colorbar(image, ax=left, label="off-diagonal term (%)", shrink=0.8)
    groups = [("single-axis sessions", pooled_errors(report, False)),
              ("multi-axis motion", pooled_errors(report, True))]
    shown = [(name, e) for name, e in groups if e is not None]
    width = 0.8 / (2 * len(shown))
    x = np.arange(3)
    for k, (name, (before, after)) in enumerate(shown):
        right.bar(x + (2 * k) * width, before, width, label=f"{name}: per-axis only", alpha=0.55)
        right.bar(x + (2 * k + 1) * width, after, width, label=f"{name}: with coupling")
    right.set_yscale("log")
    right.set_xticks(x + width * (len(shown) - 0.5), [f"axis {a}" for a in AXES])
    right.set_ylabel("held-out plateau error, rms (deg/s)")
    right.set_title("held-out error before and after the coupling")
    right.legend(fontsize=7)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=110, bbox_inches="tight")
    plt.close(fig)
    write_bytes_atomic(path, buf.getvalue())
    return path


def render(report: ImuReport, plots: list[str]) -> str:
    """report.md: the coupling with standard errors, each term in % and mrad, errors per axis."""
    lines = ["# IMU calibration (three axes)", "",
             f"Sessions: {', '.join(report.sessions)}. IMU set: `{report.coefficients}`.", "",
             f"Estimation: {report.estimation}.", "", "## Per-axis models", "",
             "| axis | model | held-out rms (deg/s) | effects |", "|---|---|---|---|"]
    for a, ax in zip(AXES, report.axes, strict=True):
        effects = ", ".join(ax.effects) or "–"
        lines.append(f"| {a} | {ax.model} | {ax.held_out_rms_dps:.4f} | {effects} |")
    lines += ["", f"## Coupling ({report.coupling_plateaus} plateaus)", "",
              "corrected = M @ (per-axis corrected rates x, y, z); each term ± its standard error.", "",
              "| | x | y | z |", "|---|---|---|---|"]
    m, se = report.matrix.tolist(), report.standard_errors.tolist()
    for i, a in enumerate(AXES):
        cells = [f"{m[i][j]:.6f} ± {se[i][j]:.1e}" for j in range(3)]
        lines.append(f"| {a} | {' | '.join(cells)} |")
    lines += ["", "| term | % | mrad | standard error (%) |", "|---|---|---|---|"]
    for t in report.off_diagonal:
        lines.append(f"| {t.row} from {t.column} | {t.percent:+.3f} | {t.mrad:+.2f} | "
                     f"{100 * t.standard_error:.4f} |")
    lines += ["", "## Held-out plateau error per axis (deg/s rms)", "",
              "Before: the per-axis models alone. After: with the coupling. Single-axis sessions: each "
              "plateau corrected with a coupling fitted without it; multi-axis motion is never fitted.", "",
              "| session | table axis | plateaus | before x | before y | before z "
              "| after x | after y | after z |",
              "|---|---|---|---|---|---|---|---|---|"]
    for e in report.held_out:
        lines.append(f"| {e.session} | {e.axis} | {e.plateaus} | "
                     + " | ".join(f"{v:.4f}" for v in e.before_rms_dps) + " | "
                     + " | ".join(f"{v:.4f}" for v in e.after_rms_dps) + " |")
    lines += [""] + [f"![{p}]({p})" for p in plots]
    return "\n".join(lines) + "\n"
