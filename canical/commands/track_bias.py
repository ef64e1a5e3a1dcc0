"""``apply --track-bias``: a recorded drive replayed through the bias tracker, as the daemon would.

Shared by the single-axis ``apply`` (one tracker for the set's axis) and the IMU set's
(:mod:`canical.commands.apply_imu`: one tracker over the three axes, so a standstill is one for
the whole vehicle). The tracker's settings are the daemon configuration's ``bias_tracking:``
with ``--config``, else the command line's; the angle random walk is the sets' own unless given.
"""

from __future__ import annotations

import argparse
import math
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
                 columns: Mapping[str, np.ndarray], rates: np.ndarray) -> np.ndarray:
    """The bias per row and axis, (rows, axes); the events printed, the report written if asked.

    ``columns`` holds time_s (since power-on), and the cue and temperature when there are.
    """
    replayer = replayer_for(args, fits, axes)
    time_s, temp, cue = tracking_inputs(args, columns)
    bias = replayer.feed(time_s, rates, temp, cue)
    out = replayer.finish()
    print_events(out, axes, bias[-1] if len(bias) else np.full(len(axes), np.nan))
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


def print_events(out, axes: tuple[str, ...], last: np.ndarray) -> None:
    """Each standstill used or refused, and a summary line with the last bias."""
    for event in out.events:
        print(f"apply: {event.line(axes, temperature=out.temperature_recorded)}")
    text = (f"{last[0]:+.4f}" if len(axes) == 1
            else ", ".join(f"{a} {b:+.4f}" for a, b in zip(axes, last, strict=True)))
    print(f"apply: bias tracking: {sum(e.decision == 'adopted' for e in out.events)} of {len(out.events)} "
          f"standstills used, {out.learned[0].updates} windows; last bias {text} deg/s"
          f"{'' if all(math.isfinite(b) for b in last) else ' (no data)'}")
