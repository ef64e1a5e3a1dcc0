"""What ``fleet analyse --propose-sets`` writes: each new set as a normal set file, and
``proposals.md`` and ``proposals.csv`` beside them (every sensor: proposed or unchanged, the
evidence, the before/after).

Why apart from :mod:`.proposal`: deciding what to propose is arithmetic on the evidence, this is
files; each new set is written through the set loader's own checks (``coefficient_file.save``
validates before it writes, atomically), so what lands on disk loads, pushes and signs.
"""

from __future__ import annotations

import csv
import io
import math
from collections.abc import Sequence
from pathlib import Path

from canical.files.atomic_file import make_dirs, write_text_atomic
from canical.fleet.proposal import PROPOSED, Proposal
from canical.sets import coefficient_file

_COLUMNS = ("sensor_id", "axis", "outcome", "reason", "set_in", "set_out", "slope_dps_per_c", "slope_se",
            "records", "power_ons", "coefficient_raw_per_c", "within_sigma_before_dps",
            "within_sigma_after_dps")


def set_name(p: Proposal) -> str:
    return f"{p.sensor_id}-{p.axis}.yaml"


def write(out: Path, proposals: Sequence[Proposal]) -> list[Path]:
    """The new sets and the two summaries in ``out``; the new sets' paths."""
    make_dirs(out)
    written = []
    for p in proposals:
        if p.outcome == PROPOSED and p.new_set is not None:
            path = out / set_name(p)
            coefficient_file.save(path, p.new_set)
            written.append(path)
    write_text_atomic(out / "proposals.csv", proposals_csv(proposals))
    write_text_atomic(out / "proposals.md", proposals_md(proposals))
    return written


def _row(p: Proposal) -> list[object]:
    e = p.evidence
    ev: list[object] = ([e.slope_dps_per_c, e.slope_se, e.records, e.power_ons] if e else ["", "", "", ""])
    return [p.sensor_id, p.axis, p.outcome, p.reason, str(p.source.path) if p.source else "",
            set_name(p) if p.outcome == PROPOSED else "", *ev,
            p.coefficient_raw_per_c if math.isfinite(p.coefficient_raw_per_c) else "",
            e.before_dps if e else "", e.after_dps if e and p.outcome == PROPOSED else ""]


def proposals_csv(proposals: Sequence[Proposal]) -> str:
    buf = io.StringIO()
    writer = csv.writer(buf, lineterminator="\n")
    writer.writerow(_COLUMNS)
    for p in proposals:
        writer.writerow([f"{v:.6g}" if isinstance(v, float) else v for v in _row(p)])
    return buf.getvalue()


def proposals_md(proposals: Sequence[Proposal]) -> str:
    """The page a calibration engineer reads before pushing: what changes, on what evidence."""
    new = [p for p in proposals if p.outcome == PROPOSED]
    lines = ["# Proposed sets from the field", "",
             f"{len(new)} new sets; {len(proposals) - len(new)} sensor axes unchanged.", "",
             "Each new set is its old set plus a `channel`/`offset` bias term on `temp_c` (reference 25 °C) "
             "that removes the temperature slope its standstills showed. *Before/after*: the standstills' "
             "bias 1σ within power-ons, on the same field records, without and with that slope.", "",
             "| sensor | axis | field slope (deg/s/°C) | ± SE | records | before (deg/s) | after (deg/s) "
             "| new set |",
             "|---|---|---|---|---|---|---|---|"]
    for p in new:
        assert p.evidence is not None
        e = p.evidence
        lines.append(f"| {p.sensor_id} | {p.axis} | {e.slope_dps_per_c:+.5f} | {e.slope_se:.5f} "
                     f"| {e.records} | {e.before_dps:.4f} | {e.after_dps:.4f} | `{set_name(p)}` |")
    signed = [p for p in new if p.source is not None and p.source.signed]
    if signed:
        lines += ["", f"{len(signed)} of the old sets were signed; the new sets are not: sign each "
                  "(`canical sign SET --key NAME.key`) before pushing it to a device that requires "
                  "signed sets."]
    lines += ["", "## Unchanged", "", "| sensor | axis | why |", "|---|---|---|"]
    lines += [f"| {p.sensor_id} | {p.axis} | {p.reason} |" for p in proposals if p.outcome != PROPOSED]
    return "\n".join(lines) + "\n"
