"""The calibration report as Markdown: what a calibration engineer reads first.

Read from top to bottom: the set that was written, the rate model alone, then each step of the
closed loop down to the written set again. Every held-out figure names its validation scheme
(whole table rates left out, on plateau means; or plateaus left out, on 2 s blocks), because
the two give different numbers for the same model.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

if TYPE_CHECKING:
    from canical.calibrate.plateaus import PlateauFinding
    from canical.calibration.calibration_report import CalibrationReport
    from canical.closed_loop.findings import Confound
    from canical.closed_loop.unexplained import Unexplained
    from canical.sessions.reference_clock import ReferenceClock


def _plateau_finding(found: PlateauFinding) -> list[str]:
    """What plateau finding estimated from the session."""
    return [
        f"- plateau finding: reference noise {found.reference_noise_dps:.3g} deg/s, tolerance "
        f"{found.rate_tol_dps:.3g} deg/s over {found.window_s:.3g} s windows; reference held "
        f"{found.reference_update_s:.3g} s, late {found.reference_latency_s:.3g} s; guards: "
        f"settle {found.settle_s:.3g} s ({_settle_source(found)}), end {found.end_guard_s:.3g} s; "
        f"{found.rate_changes} rate changes"
        + (f"; a continuous sweep, its plateaus {found.sweep_window_s:.3g} s windows"
           if found.sweep_window_s else "")
    ]


def _reference_clock(clock: ReferenceClock | None) -> list[str]:
    """How the table's own file was put on the session's clock, when it was."""
    if clock is None:
        return []
    fit = clock.fit
    return [f"- reference: `{clock.file}` on its own clock, offset {fit.offset_s:.4f} s, drift "
            f"{fit.drift_ppm:.1f} ppm, {fit.events} rate changes matched (rms {fit.residual_ms:.1f} ms)"]


def _settle_source(found: PlateauFinding) -> str:
    """Where the start guard came from: given, or the settling the sensor showed."""
    source = found.settle_source
    if source == "observed":
        return f"sensor settled in {found.observed_settling_s:.3g} s"
    return {"given": "--settle", "default": "0.5 s or a tenth of the plateau"}.get(source, source)


def render(report: CalibrationReport, plots: list[str]) -> str:
    s = report.samples
    lines = [
        "# canical calibration report",
        "",
        f"- session: `{report.session or ''}`",
        f"- coefficient set: `{report.coefficients or ''}`: {report.written_model()}",
        f"- samples used: {s.used} of {s.total} ({s.transition} at a changing rate, "
        f"{s.settling} settling); {report.plateaus} plateaus at {report.rates} rates",
        *([f"- {report.read_as_means} (a session too long to hold; see docs/sessions.md)"]
          if report.read_as_means else []),
        *_plateau_finding(report.plateau_finding),
        *(f"- left out: {p.label()}" for p in report.left_out_plateaus),
        *_reference_clock(report.reference_clock),
        f"- zero bias V0: {report.v0:.3f}",
        "",
        "## Rate model alone",
        "",
        f"{report.spec}, the size chosen by held-out error on plateau means.",
        "",
        "| | rms (deg/s) | max (deg/s) |",
        "|---|---|---|",
        f"| training, plateau means | {report.training.rms_dps:.4f} | {report.training.max_dps:.4f} |",
        f"| held-out, plateau means (whole table rates left out) | {report.held_out.rms_dps:.4f} | "
        f"{report.held_out.max_dps:.4f} |",
        "",
    ]
    lines += _segment_points(report)
    if report.closed_loop is not None:
        lines += _closed_loop(report)
    elif report.loop_skipped is not None:
        lines += [f"Closed loop skipped: {report.loop_skipped}.", ""]
    if report.allan is not None:
        from canical.calibrate.noise_records import describe  # numpy: calibrate's --help imports this module

        lines += ["## Noise: Allan deviation of the zero-rate plateaus", ""]
        lines += [f"- {line}" for line in describe(report.allan)]
        lines += ["", "Terms the τ range cannot show are not resolved; the bound is what the data allows. "
                  "Rate random walk needs records much longer than a turntable's plateaus: "
                  "use `canical noise` on a static record of an hour or more.", ""]
    if plots:
        lines += ["## Plots", ""] + [f"![{p}]({p})" for p in plots] + [""]
    return "\n".join(lines)


def _segment_points(report: CalibrationReport) -> list[str]:
    """Where the segments join: at residual extrema (with their prominence), or evenly spaced."""
    from canical.calibrate.segment_points import EVEN_SOURCE  # numpy: imported when rendering only

    points = report.segment_points
    if not points:
        return []
    if all(p.source == EVEN_SOURCE for p in points):
        head = "Segment points (evenly spaced in ΔV: a continuous sweep's windows):"
        return [head, "", *(f"- {p.rate_dps:g} deg/s (raw {p.raw:.1f})" for p in points), ""]
    return ["Segment points (from residual extrema):", "",
            *(f"- {p.rate_dps:g} deg/s (raw {p.raw:.1f}), prominence {p.prominence_dps:.4f} deg/s, {p.source}"
              for p in points), ""]


def _closed_loop(report: CalibrationReport) -> list[str]:
    """The closed loop's section: each step, the effects, the confounded groups, what is left."""
    loop = report.closed_loop
    assert loop is not None
    lines = [
        "## Closed loop: effects the model lacked",
        "",
        f"Every figure here is held-out error of {loop.method}: another scheme than the plateau "
        "means above, so the rate model alone has a figure of its own in it. Each row is one "
        "change to the model, in the order the loop made it.",
        "",
        f"| step | model | effect terms | held-out rms (deg/s), {loop.blocks_label} |",
        "|---|---|---|---|",
    ]
    for step in loop.steps:
        lines.append(f"| {step.step} | {step.spec} | {step.terms} | {step.held_out_rms_dps:.4f} |")
    lines += [
        f"| **written set** | {loop.final_spec} | {report.written.effect_terms} | "
        f"**{loop.held_out_rms_after_dps:.4f}** (max {loop.held_out_max_after_dps:.4f}) |",
        "",
    ]
    if loop.extreme_rates_in_sample_rms_dps is not None:
        lines += [f"The extreme rates train every fold (a model fitted without them would only extrapolate), "
                  "so they are in none of these figures; the written set's error there, in sample: "
                  f"{loop.extreme_rates_in_sample_rms_dps:.4f} deg/s rms.", ""]
    if report.effects:
        lines += [
            "| effect | held-out gain when added | p-value | terms (final coefficients) |",
            "|---|---|---|---|",
        ]
        for e in report.effects:
            terms = ", ".join(f"{t.feature}/{t.form} {t.coefficient:.3g}" for t in e.terms)
            ev = e.evidence
            lines.append(f"| {e.label} | {ev.held_out_gain:.0%} | {ev.p_value:.1e} | {terms} |")
    else:
        lines.append("No effect found: the residual is explained by the rate model and noise.")
    lines.append("")
    for c in report.confounded:
        lines += [
            f"**Confounded:** {' and '.join(c.candidates)} explain the same residual "
            f"(held-out rms {c.held_out_rms_before_dps:.4f} deg/s without either). "
            + _paired(c)
            + _adopted(c)
            + f"To separate them: {c.recommendation}.",
            "",
        ]
    if loop.capacity_changes:
        lines += [f"Base model grown: {', '.join(loop.capacity_changes)}.", ""]
    if loop.bias_jumps_s:
        at = ", ".join(f"{t:.0f} s" for t in loop.bias_jumps_s)
        lines += [f"**The bias jumped** during the session (at {at}): where a channel's form was judged "
                  "against the session's drift, each jump was a term of both, so that neither is judged "
                  "on the misfit around it. No jump is in the set: it is this session's, not the sensor's.",
                  ""]
    return lines + _unexplained(report.unexplained)


def _drift_reason(c: Confound) -> str:
    """Why a channel's form was not blamed: what it failed to predict, and what the set carries."""
    name, drift = c.candidates[0], c.candidates[1]
    rms = c.held_out_rms_dps
    stretches = "" if c.stretch_gain is None else (
        f", and fitted on the rest of the session it predicts {c.stretch_gain:.0%} of the residual of "
        "a stretch it did not see (a sensor's own effect repeats all session long and predicts most "
        "of it; a drift does not repeat)")
    beyond = "" if c.beyond_drift_gain is None else (
        f"; added on top of that drift it removes {max(c.beyond_drift_gain, 0.0):.0%} of what the drift "
        "leaves (a real effect of a sensor that also drifts is still there once the drift is fitted)")
    if c.beyond_drift_gain is not None and c.beyond_drift_stretch_gain is not None:
        beyond += (f", but fitted with the drift on the rest of the session it removes "
                   f"{max(c.beyond_drift_stretch_gain, 0.0):.0%} of what a drift of a stretch it did not "
                   "see leaves there (a real effect carries into it; a fit to this session's wander does "
                   "not)")
    return (f"{name} predicts the held-out plateaus to {rms[name]:.4f} deg/s against {rms[drift]:.4f} "
            f"for a drift of the session as flexible{stretches}{beyond}. No term of either is in the set: a "
            "smooth function of this session's clock is a property of the session, not of the sensor.")


def _adopted(c: Confound) -> str:
    """Which of a confounded group the set carries, and why: the attribution is ambiguous."""
    if c.drift_of_session:
        return f"**{c.adoption_rule[0].upper()}{c.adoption_rule[1:]}:** {_drift_reason(c)} "
    if c.resolved_by_user:
        return f"Added {c.resolved_by_user} as asked (--prefer); the attribution stays ambiguous. "
    if c.adopted:
        return (f"**Ambiguous attribution:** the set carries {c.adopted}, {c.adoption_rule}; it "
                "corrects this session as well as the others would, but which of them the sensor "
                "feels is not known. ")
    return f"Neither was added: {c.adoption_rule}. " if c.adoption_rule else "Neither was added. "


def _paired(c: Confound) -> str:
    """The paired test that found the held-out plateaus cannot tell the pair apart."""
    if not c.paired_p:
        return ""
    ps_text = ", ".join(f"{name} p = {p:.2g}" for name, p in c.paired_p.items())
    return (f"The held-out plateaus cannot tell {c.candidates[0]} apart from the others "
            f"(paired test, one-sided, level {c.paired_alpha:g}: {ps_text}). ")


def _unexplained(left: Unexplained | None) -> list[str]:
    """The section on what the loop could not explain, plainly."""
    if not left:
        return []
    from canical.closed_loop.unexplained import where_to_look  # numpy: calibrate's --help imports this module

    rms = left.held_out_robust_rms_dps
    head = (
        f"**Unexplained: {rms:.3g} deg/s rms, {left.ratio:.0f}× the noise floor** "
        f"({left.noise_floor_dps:.4f} deg/s, {left.noise_floor_method}). A structured residual "
        "remains that no candidate represents; do not take this calibration as complete. "
        if left.unexplained
        else f"Residual after the loop: {rms:.4f} deg/s rms, {left.ratio:.1f}× the "
        f"noise floor ({left.noise_floor_dps:.4f} deg/s, {left.noise_floor_method}): explained. "
    )
    return [
        "## What stays unexplained",
        "",
        "(Held-out residual as a robust rms, from the median squared error; plain rms "
        f"{left.held_out_rms_dps:.4f} deg/s.)",
        "",
        head + f"Where to look: {where_to_look(left)} (plot `unexplained_residual.png`: the residual "
        "against time and every candidate variable).",
        "",
    ]
