"""The daemon's field log: the trackers' decisions and power-ons kept as records for the fleet.

Why kept apart from the per-frame path: records are made and written only between frames, at
each status period, from the events the trackers already collect (the frame thread never
touches a file). A power cut loses at most the records since the last status period; a disk
that refuses a write is logged and the records wait for the next period (up to
:data:`MAX_PENDING`), the daemon carries on correcting.
"""

from __future__ import annotations

import logging
import math
from datetime import UTC, datetime, timedelta

from canical.bus.daemon_config import FieldLogConfig
from canical.errors import CanicalError
from canical.fieldlog import from_tracker
from canical.fieldlog.from_tracker import Origin
from canical.fieldlog.segments import SegmentWriter, last_power_on
from canical.tracking.tracker import BiasTracker

log = logging.getLogger("canical.serve")
#: Records kept in memory while the disk refuses them; beyond, the oldest are dropped.
MAX_PENDING = 10_000


class DaemonFieldLog:
    """One vehicle's field log: records from each generation of trackers, flushed per period."""

    def __init__(self, config: FieldLogConfig) -> None:
        self.config = config
        try:
            self.writer = SegmentWriter(config.directory, config.max_bytes)
        except OSError as exc:
            raise CanicalError(f"field_log.dir: cannot use {config.directory} "
                               f"({exc.strerror or exc})") from None
        last = last_power_on(config.directory, log.warning)
        #: The power-on count of the latest power-on: a restart of the daemon is a new one.
        self.power_on = -1 if last is None else last
        self.origin: Origin | None = None
        self._first_is_power_on = True
        self._failing = False

    def for_sets(self, sensor_id: str, set_id: int) -> None:
        """New trackers: the daemon's first ones start at a power-on, a reload's do not."""
        first = self.origin is None
        self._first_is_power_on = first
        start = self.power_on + 1 if first else self.power_on
        self.origin = Origin(self.config.vehicle_id, sensor_id, set_id, start)

    def take(self, tracker: BiasTracker, *, temperature: bool) -> None:
        """The tracker's new events as records (the caller clears the tracker's lists)."""
        if self.origin is None:
            return
        now = datetime.now(UTC)
        cycle, t_now = tracker.power_cycle, tracker.time_s

        def when(power_cycle: int, t_s: float) -> datetime:
            if power_cycle != cycle or not math.isfinite(t_now):
                return now
            return now - timedelta(seconds=max(t_now - t_s, 0.0))

        made = from_tracker.records(tracker.events, tracker.power_ons, self.origin, tracker.axes, when,
                                    temperature=temperature, with_first=self._first_is_power_on)
        for record in made:
            self.writer.add(record)
            self.power_on = max(self.power_on, record.power_on)
        del self.writer.pending[:-MAX_PENDING]

    def flush(self) -> None:
        """Write what is pending as a closed segment; a failure is logged once, retried next period."""
        try:
            self.writer.flush()
        except OSError as exc:
            if not self._failing:
                log.warning("field log %s: cannot write (%s); records kept until it can",
                            self.config.directory, exc.strerror or exc)
            self._failing = True
            return
        if self._failing:
            log.info("field log %s: writing again", self.config.directory)
        self._failing = False
