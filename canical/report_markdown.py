"""The calibration report as Markdown: what a calibration engineer reads first."""

from __future__ import annotations

from typing import Any


def _plateau_finding(found: dict[str, Any] | None) -> list[str]:
    """What plateau finding estimated from the session (empty for an older report)."""
    if not found:
        return []
    return [
        f"- plateau finding: reference noise {found['reference_noise_dps']:.3g} deg/s, tolerance "
        f"{found['rate_tol_dps']:.3g} deg/s over {found['window_s']:.3g} s windows; reference held "
        f"{found['reference_update_s']:.3g} s, late {found['reference_latency_s']:.3g} s; guards: "
        f"settle {found['settle_s']:.3g} s, end {found['end_guard_s']:.3g} s; "
        f"{found['rate_changes']} rate changes"
    ]


def render(report: dict[str, Any], plots: list[str]) -> str:
    s = report["samples"]
    lines = [
        "# canical calibration report",
        "",
        f"- session: `{report.get('session', '')}`",
        f"- model: {report['spec']}",
        f"- samples used: {s['used']} of {s['total']} ({s['transition']} at a changing rate, "
        f"{s['settling']} settling); {report['plateaus']} plateaus at {report['rates']} rates",
        *_plateau_finding(report.get("plateau_finding")),
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
                lines.append(
                    f"| {e['name']} | {e['rms_before_dps']:.4f} | {e['rms_after_dps']:.4f} | "
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
    elif loop:
        lines += [f"Closed loop skipped: {loop['skipped']}.", ""]
    if plots:
        lines += ["## Plots", ""] + [f"![{p}]({p})" for p in plots] + [""]
    return "\n".join(lines)
