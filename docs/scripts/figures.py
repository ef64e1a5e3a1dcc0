"""The science pages' figures, made from canical's own code on simulated sessions at build time.

Each function returns PNG bytes; :func:`figures` returns all of them by their path under
``docs/`` (the MkDocs hook adds them to the site; nothing is committed). Run this file to write
them into a folder and look at them: ``python docs/scripts/figures.py --out DIR``.

The sessions are the demo's (the paper's protocol: −60…60 deg/s in 3 deg/s steps), shortened
where that changes nothing a figure shows, so the whole set takes seconds.
"""

from __future__ import annotations

import argparse
import io
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]
if str(ROOT) not in sys.path:
    sys.path.insert(0, str(ROOT))

import matplotlib  # noqa: E402

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402

DPI = 100


def png(fig) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def models_figure() -> bytes:
    """The paper's three models fitted on one session, judged on a second at rates between."""
    from canical.calibrate.cross_validation import prediction_errors
    from canical.calibration.evaluation import PAPER_MODELS, held_out_points
    from canical.calibration.pipeline import fit_base
    from canical.sim.sessions import between_rates_session, paper_session

    train, test = paper_session(seed=0, dwell_s=3.0), between_rates_session(seed=1, dwell_s=3.0)
    fig, axes = plt.subplots(2, 1, figsize=(8, 6.4), sharex=True)
    for label, options in PAPER_MODELS:
        base = fit_base(train, options)
        points = held_out_points(test, base.v0)
        errors = prediction_errors(base.fitted.model, points)
        rms = float(np.sqrt(np.mean(errors**2)))
        ax = axes[0] if label.startswith(("forward", "segmented-linear")) else axes[1]
        ax.plot(points.rate, errors, "o-", ms=3, lw=1, label=f"{label}: rms {rms:.4f} deg/s")
    for ax in axes:
        ax.axhline(0, color="k", lw=0.5)
        ax.set_ylabel("error (deg/s)")
        ax.grid(True, alpha=0.3)
        ax.legend(fontsize=8, loc="best")
    axes[0].set_title(
        "the forward polynomial (eq. 5) and the common segmented-linear model (eq. 6)", fontsize=10
    )
    axes[1].set_title(
        "the segmented inverse polynomial (eq. 11): the paper's 4 segments, and canical's default",
        fontsize=10,
    )
    axes[1].set_xlabel("table rate (deg/s)")
    fig.suptitle(
        "Error of each model on held-out plateaus\n(held out: a second session at the rates midway "
        "between the training rates)",
        fontsize=10,
    )
    fig.tight_layout()
    return png(fig)


def segment_points_figure() -> bytes:
    """The paper's section IV: a global quadratic's residual, its prominent extrema, the segment points."""
    from canical.calibrate.segment_points import PROMINENCE_SIGMA, global_quadratic_residual, rate_noise
    from canical.calibration.pipeline import CalibrateOptions, fit_base
    from canical.sim.sessions import paper_session

    base = fit_base(
        paper_session(seed=0, dwell_s=3.0), CalibrateOptions(segments=4, order=2, smoothness=None)
    )
    merged = base.points.by_rate()
    resid = global_quadratic_residual(merged)
    floor = PROMINENCE_SIGMA * float(np.median(rate_noise(merged)))
    fig, ax = plt.subplots(figsize=(8, 4.2))
    ax.plot(merged.rate, resid, "o-", ms=3, lw=1, label="residual of one quadratic ω(ΔV) over the span")
    labels = {
        "global-quadratic": "segment point at an extremum of this residual",
        "segmented-residual": "further point, at an extremum of the segmented fit's residual",
    }
    for ext in base.fitted.extrema:
        colour = "C3" if ext.source == "global-quadratic" else "C2"
        ax.axvline(ext.rate_dps, color=colour, lw=1, ls="--", label=labels.pop(ext.source, None))
        ax.annotate(
            f"{ext.rate_dps:+.0f} deg/s\nprominence {ext.prominence_dps:.3f}",
            (ext.rate_dps, float(np.interp(ext.rate_dps, merged.rate, resid))),
            textcoords="offset points",
            xytext=(4, 8),
            fontsize=7,
            color=colour,
        )
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("table rate (deg/s)")
    ax.set_ylabel("residual (deg/s)")
    ax.set_title(
        f"Segment points at the extrema of a global quadratic fit's residual "
        f"(an extremum counts above {floor:.4f} deg/s of prominence: {PROMINENCE_SIGMA:g} standard "
        f"errors)\n(all training plateaus, nothing held out)",
        fontsize=9,
    )
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    return png(fig)


def continuity_figure() -> bytes:
    """Free joins (the paper's) jump at a segment point; C0 joins meet, C1 joins also share slopes."""
    from canical.calibration.pipeline import CalibrateOptions, fit_base
    from canical.sim.sessions import paper_session

    session = paper_session(seed=0, dwell_s=3.0)
    fits = {
        name: fit_base(session, CalibrateOptions(segments=4, order=2, smoothness=s)).fitted.model
        for name, s in (
            ("free joins (the paper's)", None),
            ("C0: continuous", 0),
            ("C1: continuous slope", 1),
        )
    }
    reference = fits["C1: continuous slope"]
    knot = float(reference.knots[len(reference.knots) // 2])
    half = 0.04 * (reference.span[1] - reference.span[0])
    fig, axes = plt.subplots(1, len(fits), figsize=(11, 3.6), sharey=False)
    for ax, (name, model) in zip(axes, fits.items(), strict=True):
        k = float(model.knots[np.argmin(np.abs(model.knots - knot))])
        dv = np.linspace(k - half, k + half, 801)
        rate = model.evaluate(dv)[0]
        slope = (rate[-1] - rate[0]) / (dv[-1] - dv[0])
        jump = float(model.jumps()[np.argmin(np.abs(model.knots - knot))]) if hasattr(model, "jumps") else 0.0
        ax.plot(dv - k, rate - (rate[0] + slope * (dv - dv[0])), lw=1.2)
        ax.axvline(0, color="C3", ls="--", lw=1)
        ax.set_title(f"{name}\njump at the point {abs(jump):.4f} deg/s", fontsize=9)
        ax.set_xlabel("ΔV − segment point (raw units)")
        ax.set_ylabel("rate minus its chord (deg/s)")
        ax.grid(True, alpha=0.3)
    fig.suptitle(
        "The corrected rate across a segment point, 4 segments, quadratic (fitted on all plateaus)",
        fontsize=10,
    )
    fig.tight_layout()
    return png(fig)


def closed_loop_figures() -> dict[str, bytes]:
    """The report's own plots for the demo's sensor with an undeclared temperature effect."""
    from canical.calibration.pipeline import CalibrateOptions, calibrate
    from canical.report.plots import write_plots
    from canical.sim.scenarios import SCENARIOS

    scenario = next(s for s in SCENARIOS if s.name.startswith("temperature bias + scale"))
    result = calibrate(scenario.session(0, dwell_s=3.0), CalibrateOptions(), sensor_id="SIM-0001", axis="z")
    assert result.loop is not None
    out: dict[str, bytes] = {}
    with tempfile.TemporaryDirectory() as folder:
        for path in write_plots(result.loop, Path(folder)):
            if path.name.startswith(("residual_vs_rate", "effect_1", "unexplained")):
                name = "effect.png" if path.name.startswith("effect_1") else path.name
                out[name.replace("_", "-")] = path.read_bytes()
    return out


def allan_figure() -> bytes:
    """Allan deviation of a simulated two-hour record at rest: white noise and a rate random walk."""
    from canical.calibrate.noise_records import noise_analysis
    from canical.report.allan_plot import write_allan_plot

    fs, hours = 50.0, 2.0
    n = int(fs * 3600 * hours)
    rng = np.random.default_rng(0)
    arw_deg_rt_h, rrw_deg_h_rt_h = 0.3, 4.0
    white = rng.normal(0.0, arw_deg_rt_h / 60.0 * np.sqrt(fs), n)  # deg/s: ARW/60 per √s
    walk = np.cumsum(rng.normal(0.0, rrw_deg_h_rt_h / 3600.0 / 60.0 / np.sqrt(fs), n))
    analysis = noise_analysis([white + walk], 1.0 / fs, "simulated record at rest")
    with tempfile.TemporaryDirectory() as folder:
        path = write_allan_plot(
            analysis,
            Path(folder) / "allan.png",
            title=f"Simulated rest record (ARW {arw_deg_rt_h} deg/√h, RRW {rrw_deg_h_rt_h} deg/h/√h)",
        )
        return path.read_bytes()


def figures() -> dict[str, bytes]:
    """Every figure, by its path under ``docs/``."""
    out = {
        "science/img/models.png": models_figure(),
        "science/img/segment-points.png": segment_points_figure(),
        "science/img/continuity.png": continuity_figure(),
        "science/img/allan.png": allan_figure(),
    }
    for name, data in closed_loop_figures().items():
        out[f"science/img/{name}"] = data
    return out


def main() -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, required=True, help="folder to write the figures into")
    args = parser.parse_args()
    for rel, data in figures().items():
        path = args.out / rel
        path.parent.mkdir(parents=True, exist_ok=True)
        path.write_bytes(data)
        print(path)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
