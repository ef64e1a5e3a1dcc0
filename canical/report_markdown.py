"""The calibration report as Markdown: what a calibration engineer reads first."""

from __future__ import annotations

from typing import Any

from canical.unexplained import where_to_look


def render(report: dict[str, Any], plots: list[str]) -> str:
    s = report["samples"]
    lines = [
        "# canical calibration report",
        "",
        f"- session: `{report.get('session', '')}`",
        f"- model: {report['spec']}",
        f"- samples used: {s['used']} of {s['total']} ({s['transition']} at a changing rate, "
        f"{s['settling']} settling); {report['plateaus']} plateaus at {report['rates']} rates",
        f"- zero bias V0: {report['v0']:.3f}",
        "",
        "## Rate model (held-out table rates)",
        "",
        "| | rms (deg/s) | max (deg/s) |",
        "|---|---|---|",
        f"| training | {report['training']['rms_dps']:.4f} | {report['training']['max_dps']:.4f} |",
        f"| held-out | {report['held_out']['rms_dps']:.4f} | {report['held_out']['max_dps']:.4f} |",
        "",
    ]
    if report.get("segment_points"):
        lines += ["Segment points (from residual extrema):", ""]
        lines += [
            f"- {p['rate_dps']:g} deg/s (raw {p['raw']:.1f}), prominence {p['prominence_dps']:.4f}"
            f" deg/s, {p['source']}"
            for p in report["segment_points"]
        ]
        lines.append("")
    loop = report.get("closed_loop")
    if loop and "skipped" not in loop:
        before = f"{loop['held_out_rms_before_dps']:.4f} | {loop['held_out_max_before_dps']:.4f}"
        after = f"{loop['held_out_rms_after_dps']:.4f} | {loop['held_out_max_after_dps']:.4f}"
        lines += [
            "## Closed loop: effects the model lacked",
            "",
            f"Final model: {loop['final_spec']}, plus the effect terms below.",
            "",
            f"Held-out error ({loop['method']}):",
            "",
            "| | rms (deg/s) | max (deg/s) |",
            "|---|---|---|",
            f"| rate model only | {before} |",
            f"| with effects | {after} |",
            "",
        ]
        if report["effects"]:
            lines += [
                "| effect | held-out rms before | after | gain | p-value | terms |",
                "|---|---|---|---|---|---|",
            ]
            for e in report["effects"]:
                terms = ", ".join(f"{t['feature']}/{t['form']} {t['coefficient']:.3g}" for t in e["terms"])
                ev = e["evidence"]
                name = e.get("description", e["name"])
                lines.append(
                    f"| {name} | {e['rms_before_dps']:.4f} | {e['rms_after_dps']:.4f} | "
                    f"{ev['held_out_gain']:.0%} | {ev['p_value']:.1e} | {terms} |"
                )
        else:
            lines.append("No effect found: the residual is explained by the rate model and noise.")
        lines.append("")
        for c in report.get("confounded", []):
            lines += [
                f"**Confounded:** {' and '.join(c['candidates'])} explain the same residual "
                f"(held-out rms {c['held_out_rms_before_dps']:.4f} deg/s without either). "
                + (
                    "Neither was added. "
                    if not c["resolved_by_user"]
                    else f"Added {c['resolved_by_user']} as asked (--prefer). "
                )
                + f"To separate them: {c['recommendation']}.",
                "",
            ]
        if loop["capacity_changes"]:
            lines += [f"Base model grown: {', '.join(loop['capacity_changes'])}.", ""]
        lines += _unexplained(report.get("unexplained"))
    elif loop:
        lines += [f"Closed loop skipped: {loop['skipped']}.", ""]
    if plots:
        lines += ["## Plots", ""] + [f"![{p}]({p})" for p in plots] + [""]
    return "\n".join(lines)


def _unexplained(left: dict[str, Any] | None) -> list[str]:
    """The section on what the loop could not explain, plainly."""
    if not left:
        return []
    rms = left["held_out_robust_rms_dps"]
    head = (
        f"**Unexplained: {rms:.3g} deg/s rms, {left['ratio']:.0f}× the noise floor** "
        f"({left['noise_floor_dps']:.4f} deg/s, {left['noise_floor_method']}). A structured residual "
        "remains that no candidate represents; do not take this calibration as complete. "
        if left["unexplained"]
        else f"Residual after the loop: {rms:.4f} deg/s rms, {left['ratio']:.1f}× the "
        f"noise floor ({left['noise_floor_dps']:.4f} deg/s, {left['noise_floor_method']}): explained. "
    )
    return [
        "## What stays unexplained",
        "",
        "(Held-out residual as a robust rms, from the median squared error; plain rms "
        f"{left['held_out_rms_dps']:.4f} deg/s.)",
        "",
        head + f"Where to look: {where_to_look(left)} (plot `unexplained_residual.png`: the residual "
        "against time and every candidate variable).",
        "",
    ]
