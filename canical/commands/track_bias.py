"""``apply --track-bias``: a recorded drive replayed through the bias tracker, as the daemon would.

Shared by the single-axis ``apply`` (one tracker for the set's axis) and the IMU set's
(:mod:`canical.commands.apply_imu`: one tracker over the three axes, so a standstill is one for
the whole vehicle). The tracker's settings are the daemon configuration's ``bias_tracking:``
with ``--config``, else the command line's; the angle random walk is the sets' own unless given.
"""

from __future__ import annotations

import argparse
import math
import sys
from collections.abc import Mapping, Sequence
from dataclasses import replace
from typing import Any

import numpy as np

from canical.errors import CanicalError


def tracker_config(args: argparse.Namespace, fits: Sequence[Mapping[str, Any]]):
    """The tracker's settings for these sets (their fit sections). With several axes one
    tracker decides for all: the noisiest axis's angle random walk tells a standstill."""
    from canical.tracking.config import TrackerConfig

    settings = getattr(args, "daemon_tracking", None)  # the daemon configuration's bias_tracking
    if settings is not None:
        return settings.tracker.for_sets(fits, arw_given=settings.arw_given)
    try:
        arw = args.arw if args.arw is not None else TrackerConfig.arw_deg_rt_h
        cue_below = args.standstill_below if args.standstill_column else None
        config = TrackerConfig(arw_deg_rt_h=arw, cue_threshold=cue_below)
    except ValueError as exc:
        raise CanicalError(f"bias tracking: {exc}") from None
    return config.for_sets(fits, arw_given=args.arw is not None)


def tracked_bias(args: argparse.Namespace, fits: Sequence[Mapping[str, Any]], axes: tuple[str, ...],
                 columns: Mapping[str, np.ndarray], rates: np.ndarray, source: tuple[str, int]) -> np.ndarray:
    """The bias per row and axis, (rows, axes); the events printed, the report and the field log
    written if asked. ``source`` is the sensor's id and the set's.

    ``columns`` holds time_s (since power-on), and the cue and temperature when there are.
    """
    replayer = replayer_for(args, fits, axes)
    time_s, temp, cue = tracking_inputs(args, columns)
    bias = replayer.feed(time_s, rates, temp, cue)
    out = replayer.finish()
    print_events(out, axes, bias[-1] if len(bias) else np.full(len(axes), np.nan))
    write_field_log(args, out, axes, source)
    if args.report_dir:
        from canical.report.drive import write_drive_report

        write_drive_report(args.report_dir, time_s, rates, replace(out, bias_dps=bias), axes)
    return bias


def replayer_for(args: argparse.Namespace, fits: Sequence[Mapping[str, Any]], axes: tuple[str, ...]):
    """The tracker for these sets, fed a drive block by block (:class:`~canical.tracking.replay.Replayer`)."""
    from canical.tracking.replay import Replayer

    return Replayer(tracker_config(args, fits), axes=axes)


def tracking_inputs(args: argparse.Namespace, columns: Mapping[str, np.ndarray]
                    ) -> tuple[np.ndarray, np.ndarray | None, np.ndarray | None]:
    """A block's time since power-on, temperature and cue, from its columns (checked finite time)."""
    time_s = columns["time_s"]
    if not np.isfinite(time_s).all():
        raise CanicalError(f"{args.input}: time_s has empty or non-numeric values")
    cue = columns[args.standstill_column] if args.standstill_column else None
    return time_s, columns.get(args.temp_column), cue


def write_field_log(args: argparse.Namespace, out, axes: tuple[str, ...], source: tuple[str, int]) -> None:
    """With ``--field-log DIR``: the drive's standstill decisions and power-ons as the daemon's
    records, in a new segment (the power-on count continuing the folder's)."""
    if not getattr(args, "field_log", None):
        return
    from datetime import UTC, datetime, timedelta
    from pathlib import Path

    from canical.fieldlog import from_tracker
    from canical.fieldlog.segments import SegmentWriter, last_power_on

    if args.drive_start:
        start = _utc(args.drive_start)
    else:  # the file was written when the drive ended
        ended = datetime.fromtimestamp(Path(args.input).stat().st_mtime, UTC)
        start = ended - timedelta(seconds=from_tracker.drive_seconds(out.power_ons, out.end_s))
    last = last_power_on(Path(args.field_log), lambda line: print(f"apply: {line}", file=sys.stderr))
    origin = from_tracker.Origin(args.vehicle_id, source[0], source[1], 0 if last is None else last + 1)
    writer = SegmentWriter(Path(args.field_log), max_bytes=2**62)  # offline: nothing rotated away
    made = from_tracker.records(out.events, out.power_ons, origin, axes,
                                from_tracker.drive_clock(out.power_ons, start),
                                temperature=out.temperature_recorded)
    for record in made:
        writer.add(record)
    writer.flush()
    stops = sum(r.decision != "power-on" for r in made)
    first = origin.first_power_on
    print(f"apply: field log: {len(made)} records ({stops} standstills, power-ons {first}.."
          f"{first + out.power_cycles - 1}) into {args.field_log}")


def _utc(text: str):
    """``--drive-start``: an ISO 8601 time, UTC unless it says otherwise."""
    from datetime import UTC, datetime

    try:
        when = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError:
        raise CanicalError(f"--drive-start {text!r}: not an ISO 8601 time (2026-11-27T08:00:00Z)") from None
    return when if when.tzinfo is not None else when.replace(tzinfo=UTC)


def print_events(out, axes: tuple[str, ...], last: np.ndarray) -> None:
    """Each standstill used or refused, and a summary line with the last bias."""
    for event in out.events:
        print(f"apply: {event.line(axes, temperature=out.temperature_recorded)}")
    text = (f"{last[0]:+.4f}" if len(axes) == 1
            else ", ".join(f"{a} {b:+.4f}" for a, b in zip(axes, last, strict=True)))
    print(f"apply: bias tracking: {sum(e.decision == 'adopted' for e in out.events)} of {len(out.events)} "
          f"standstills used, {out.learned[0].updates} windows; last bias {text} deg/s"
          f"{'' if all(math.isfinite(b) for b in last) else ' (no data)'}")
