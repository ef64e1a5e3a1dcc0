"""The fleet analysis's outputs: ``sensors.csv`` (one row per sensor axis), ``report.md`` a fleet
engineer reads at a glance (verdicts, the sensors listed for maintenance, per lot), and plots.

Why per lot: a lot's sensors share their part's behaviour. A lot is what a sensor table says
(``--lots CSV``), else the sensor id's prefix: ``B25-00042`` names its lot before the dash; an id
without one is its own lot.
"""

from __future__ import annotations

import csv
import dataclasses
import io
import math
from collections.abc import Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from canical.errors import CanicalError
from canical.files.atomic_file import make_dirs, write_bytes_atomic, write_text_atomic
from canical.fleet.analysis import (
    DRIFT_LIMIT,
    DRIFTING,
    IN_SPEC,
    OUT_OF_SPEC,
    SLOPE_LIMIT,
    SPREAD_LIMIT,
    TOO_LITTLE,
    SensorVerdict,
)

VERDICTS = (IN_SPEC, DRIFTING, OUT_OF_SPEC, TOO_LITTLE)


@dataclass(frozen=True)
class Lots:
    """Which lot each sensor is from: a sensor table's (``--lots``), else its id's prefix."""

    table: Mapping[str, str] = field(default_factory=dict)

    def of(self, sensor_id: str) -> str:
        if sensor_id in self.table:
            return self.table[sensor_id]
        return sensor_id.partition("-")[0] if "-" in sensor_id else sensor_id


def read_lots(path: Path) -> Lots:
    """A sensor table: a CSV with ``sensor_id`` and ``lot`` columns (others ignored)."""
    try:
        with path.open(newline="", encoding="utf-8") as handle:
            table = list(csv.DictReader(handle))
    except (OSError, UnicodeDecodeError, csv.Error) as exc:
        raise CanicalError(f"--lots {path}: cannot read ({exc})") from None
    if not table or not {"sensor_id", "lot"} <= set(table[0]):
        raise CanicalError(f"--lots {path}: a CSV with sensor_id and lot columns")
    return Lots({row["sensor_id"]: row["lot"] for row in table})


def sensors_csv(verdicts: Sequence[SensorVerdict], lots: Lots) -> str:
    """One row per sensor axis, numbers written with repr's precision (the same run, the same bytes)."""
    text = io.StringIO()
    fields = [f.name for f in dataclasses.fields(SensorVerdict)]
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(["sensor_id", "axis", "lot", *fields[2:]])
    for v in verdicts:
        values = [getattr(v, f) for f in fields]
        writer.writerow([v.sensor_id, v.axis, lots.of(v.sensor_id), *(_cell(x) for x in values[2:])])
    return text.getvalue()


def _cell(value: object) -> str:
    if isinstance(value, float):
        return "" if math.isnan(value) else repr(value)
    return str(value)


def report_md(verdicts: Sequence[SensorVerdict], source: str, lots: Lots) -> str:
    """The report: counts per verdict, the sensors for maintenance, per lot, the plots."""
    counts = {name: sum(v.verdict == name for v in verdicts) for name in VERDICTS}
    lines = [f"# Fleet analysis of {source}", "",
             f"{len(verdicts)} sensor axes, {sum(v.records for v in verdicts)} adopted standstills, "
             f"{sum(v.power_ons for v in verdicts)} power-ons.", "",
             "| verdict | sensors |", "|---|---|", *(f"| {k} | {n} |" for k, n in counts.items()), "",
             f"Out of spec: turn-on spread (1σ) beyond {SPREAD_LIMIT:g} deg/s, or a temperature slope left "
             f"by the set beyond {SLOPE_LIMIT:g} deg/s/°C by more than two standard errors. Drifting: a bias "
             f"drift beyond {DRIFT_LIMIT:g} deg/s per operating hour and four standard errors. Too little "
             "evidence: fewer than 10 standstills or 3 power-ons.", "",
             "## Listed for maintenance", ""]
    flagged = [v for v in verdicts if v.verdict in (OUT_OF_SPEC, DRIFTING)]
    lines += ["| sensor | axis | verdict | spread deg/s | slope deg/s/°C (± SE) | drift deg/s/h (± SE) |",
              "|---|---|---|---|---|---|"]
    lines += [f"| {v.sensor_id} | {v.axis} | {v.verdict} | {v.spread_dps:.3f} | {v.slope_dps_per_c:+.4f} "
              f"± {v.slope_se:.4f} | {v.drift_dps_per_h:+.4f} ± {v.drift_se:.4f} |" for v in flagged]
    if not flagged:
        lines.append("| none | | | | | |")
    lines += ["", "## Per lot", "", *_GROUP_HEAD.replace("GROUP", "lot").splitlines()]
    lines += [_lot_row(lot, [v for v in verdicts if lots.of(v.sensor_id) == lot])
              for lot in sorted({lots.of(v.sensor_id) for v in verdicts})]
    lines += ["", "## Per set id", "", *per_set_id(verdicts)]
    lines += ["", "![turn-on spread](spread.png)", "", "![temperature slope](slope.png)", "",
              "![drift](drift.png)", ""]
    return "\n".join(lines)


_GROUP_HEAD = ("| GROUP | sensors | in spec | drifting | out of spec | spread deg/s: median (10–90 %) "
               "| slope deg/s/°C: median (10–90 %) |\n|---|---|---|---|---|---|---|")


def _lot_row(lot: str, mine: Sequence[SensorVerdict]) -> str:
    counts = " | ".join(str(sum(v.verdict == k for v in mine)) for k in (IN_SPEC, DRIFTING, OUT_OF_SPEC))
    spread = _spread_of([v.spread_dps for v in mine], "{:.3f}")
    slope = _spread_of([v.slope_dps_per_c for v in mine], "{:+.4f}")
    return f"| {lot} | {len(mine)} | {counts} | {spread} | {slope} |"


def _spread_of(values: Sequence[float], fmt: str) -> str:
    """A distribution in a cell: the median and the 10th and 90th percentiles."""
    finite = [x for x in values if math.isfinite(x)]
    if not finite:
        return "–"
    p10, p50, p90 = (float(x) for x in np.percentile(finite, [10, 50, 90]))
    return f"{fmt.format(p50)} ({fmt.format(p10)} to {fmt.format(p90)})"


def per_set_id(verdicts: Sequence[SensorVerdict]) -> list[str]:
    """Per set id shared by several sensors (one calibration generation): the distributions.

    Why only shared ones: a set is usually one sensor's calibration, so a set id names one sensor
    and its distribution is that sensor's row; a set id several sensors carry (the same set pushed
    to a batch, or an IMU's combined id) is where a generation's behaviour shows."""
    groups: dict[int, list[SensorVerdict]] = {}
    for v in verdicts:
        groups.setdefault(v.set_id, []).append(v)
    shared = {k: g for k, g in sorted(groups.items()) if len(g) > 1}
    if not shared:
        return [f"Every set id here is one sensor's ({len(groups)} set ids, {len(verdicts)} sensor axes): "
                "no generation is shared, so there is no distribution per set id."]
    rows = [_lot_row(f"0x{k:08x}", g) for k, g in shared.items()]
    alone = len(groups) - len(shared)
    return [*_GROUP_HEAD.replace("GROUP", "set id").splitlines(), *rows, "",
            f"{alone} further set ids are one sensor's each."]


def write(report_dir: Path, verdicts: Sequence[SensorVerdict], source: str, lots: Lots) -> None:
    """``sensors.csv``, ``report.md`` and the three plots into ``report_dir``."""
    make_dirs(report_dir)
    write_text_atomic(report_dir / "sensors.csv", sensors_csv(verdicts, lots))
    write_text_atomic(report_dir / "report.md", report_md(verdicts, source, lots))
    for name, png in plots(verdicts, lots).items():
        write_bytes_atomic(report_dir / name, png)


def plots(verdicts: Sequence[SensorVerdict], lots: Lots) -> dict[str, bytes]:
    """Spread per lot, slope against its standard error, drift per sensor: each as PNG bytes."""
    return {"spread.png": _spread_plot(verdicts, lots), "slope.png": _slope_plot(verdicts),
            "drift.png": _drift_plot(verdicts)}


COLOURS = {IN_SPEC: "tab:green", DRIFTING: "tab:orange", OUT_OF_SPEC: "tab:red", TOO_LITTLE: "tab:grey"}


def _axes() -> Any:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt.subplots(figsize=(7, 4))


def _spread_plot(verdicts: Sequence[SensorVerdict], lots: Lots) -> bytes:
    names = sorted({lots.of(v.sensor_id) for v in verdicts})
    fig, ax = _axes()
    data = [[v.spread_dps for v in verdicts if lots.of(v.sensor_id) == lot and math.isfinite(v.spread_dps)]
            for lot in names]
    ax.hist(data, bins=40, stacked=True, label=names)
    ax.axvline(SPREAD_LIMIT, color="tab:red", linestyle="--", label="spec")
    ax.set(xlabel="turn-on bias spread, 1σ (deg/s)", ylabel="sensors", title="Turn-on bias spread per lot")
    ax.legend()
    return _png(fig)


def _slope_plot(verdicts: Sequence[SensorVerdict]) -> bytes:
    fig, ax = _axes()
    for name in VERDICTS:
        mine = [v for v in verdicts if v.verdict == name and math.isfinite(v.slope_dps_per_c)]
        ax.plot([v.slope_dps_per_c for v in mine], [v.slope_se for v in mine], "o", ms=3,
                color=COLOURS[name], label=name)
    for limit in (-SLOPE_LIMIT, SLOPE_LIMIT):
        ax.axvline(limit, color="tab:red", linestyle="--")
    ax.set(xlabel="temperature slope left by the set (deg/s/°C)", ylabel="its standard error (deg/s/°C)",
           title="Field temperature slope per sensor")
    ax.legend()
    return _png(fig)


def _drift_plot(verdicts: Sequence[SensorVerdict]) -> bytes:
    fig, ax = _axes()
    for name in VERDICTS:
        mine = [v for v in verdicts if v.verdict == name and math.isfinite(v.drift_dps_per_h)]
        ax.plot([v.hours for v in mine], [v.drift_dps_per_h for v in mine], "o", ms=3, color=COLOURS[name],
                label=name)
    ax.set(xlabel="operating hours observed (h)", ylabel="bias drift (deg/s per h)",
           title="Bias drift with operating hours")
    ax.legend()
    return _png(fig)


def _png(fig: Any) -> bytes:
    import matplotlib.pyplot as plt

    buffer = io.BytesIO()
    fig.tight_layout()
    fig.savefig(buffer, format="png", dpi=100, metadata={"Software": None})
    plt.close(fig)
    return buffer.getvalue()
