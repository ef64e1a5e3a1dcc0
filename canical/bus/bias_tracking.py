"""The bias learned at standstills, on the bus: one tracker per calibrated axis, fed per raw frame,
or one over the three axes for an IMU set.

Why per axis: ``canical apply SET LOG --track-bias`` replays one axis's set, so the daemon tracks
each axis on its own with exactly the same steps (:meth:`canical.tracking.tracker.BiasTracker.step`
on the same corrected rate, time, temperature and cue), and the two give the same bias bit for
bit. An IMU set is applied as one (``apply imu.yaml --track-bias``: one tracker, a standstill is
the vehicle's), so with one the daemon runs one tracker over its three coupled rates. A
tracker steps only on frames where its axis is calibrated and the tracking's inputs have
arrived (the frames ``apply`` keeps). Between frames the daemon logs each standstill adopted or
refused, puts each axis's learned bias in systemd's STATUS, and keeps the learned state in the
state file (:mod:`canical.tracking.state_file`), keyed by the sets' combined id: new sets start
afresh, with one log line.
"""

from __future__ import annotations

import logging
import math
from collections.abc import Mapping
from typing import Any

from canical.bus.daemon_config import BiasTracking
from canical.bus.field_log import DaemonFieldLog
from canical.bus.status import AXIS_CODES
from canical.tracking import state_file
from canical.tracking.fast_step import FastStep, FastStep3, fast_step, fast_step3
from canical.tracking.tracker import BiasTracker

log = logging.getLogger("canical.serve")
NAN = math.nan


class DaemonTracking:
    """The daemon's trackers for one generation of sets, and what it does with them between frames."""

    def __init__(self, config: BiasTracking, values: dict[str, float],
                 field_log: DaemonFieldLog | None = None) -> None:
        self.config = config
        self.values = values
        self.field_log = field_log
        self.set_id: int | None = None
        self.axes: tuple[str, ...] = ()
        self.trackers: list[BiasTracker | None] = [None, None, None]
        #: Time zero without a time input: the first frame's stamp (the generated handler sets it too).
        self.t0: float | None = None
        self._saved_updates = -1
        #: Per frame: the inputs' names (time, temperature, cue), and per axis its step and the bias
        #: it applies now (for a frame the tracking's inputs have not all reached).
        self._names = (config.time_input, config.temperature_input, config.settings.cue_input)
        self._fast: list[FastStep | None] = [None, None, None]
        self._steps: list[tuple[Any, Any]] = [(None, None)] * 3
        self._joint: FastStep3 | None = None  # an IMU set's one tracker over three axes

    def for_sets(self, combined_id: int, axes: tuple[str, ...],
                 fits: tuple[Mapping[str, Any] | None, ...], *, joint: bool = False,
                 sensor: str = "") -> None:
        """New sets: save what was learned for the old ones, load (or start) the new ones' state.

        ``fits`` holds each axis's set's ``fit`` section (None: the axis is not calibrated); each
        tracker tells a standstill by its own set's angle random walk unless the configuration
        gives one. ``joint`` (an IMU set, every axis calibrated): one tracker over the three
        axes, telling a standstill by the noisiest axis's, as ``apply`` does."""
        if combined_id == self.set_id:
            return
        self.log_events()  # the old trackers' last records, before they go
        self.save()
        if self.field_log is not None:
            self.field_log.for_sets(sensor, combined_id)
        self.set_id, self.axes = combined_id, axes
        learned = None
        if self.config.state_file is not None:
            loaded = state_file.load(self.config.state_file, combined_id, axes,
                                     state_file.StateLimits.of(self.config.settings.tracker))
            log.log(logging.WARNING if loaded.refused else logging.INFO, "%s", loaded.note)
            learned = loaded.learned
        settings = self.config.settings
        if joint:
            tracker = BiasTracker(axes, settings.tracker.for_sets([f for f in fits if f is not None],
                                                                  arw_given=settings.arw_given), learned)
            self.trackers, self._fast, self._steps = [tracker], [None, None, None], [(None, None)] * 3
            self._joint = fast_step3(tracker)
            self._saved_updates = self._updates()
            return
        self._joint = None
        self.trackers = [
            BiasTracker((axis,), settings.tracker.for_set(fit, arw_given=settings.arw_given),
                        None if learned is None else (learned[k],))
            if fit is not None else None for k, (axis, fit) in enumerate(zip(axes, fits, strict=True))]
        self._fast = [None if t is None else fast_step(t) for t in self.trackers]
        self._steps = [(None, None) if f is None else (f.step, f.applied) for f in self._fast]
        self._saved_updates = self._updates()

    def __call__(self, stamp: float, r0: float, r1: float, r2: float, u0: bool, u1: bool,
                 u2: bool) -> tuple[float, float, float]:
        """The three rates less each tracked axis's bias (per frame); an uncalibrated axis is left be."""
        values = self.values
        time_name, temp_name, cue_name = self._names
        if time_name is None:
            if self.t0 is None:
                self.t0 = stamp
            t = stamp - self.t0
        else:
            t = values.get(time_name, NAN)
        temp = NAN if temp_name is None else values.get(temp_name, NAN)
        cue = None if cue_name is None else values.get(cue_name)
        ready = t == t and (temp_name is None or temp == temp) and (cue_name is None or cue is not None)
        joint = self._joint
        if joint is not None:
            if u0:  # an IMU set's axes are calibrated together, or none is
                return r0, r1, r2
            b0, b1, b2 = joint.step(t, r0, r1, r2, temp, cue) if ready else joint.applied()
            return r0 - b0, r1 - b1, r2 - b2
        (s0, a0), (s1, a1), (s2, a2) = self._steps
        if s0 is not None and not u0:
            r0 -= s0(t, r0, temp, cue) if ready else a0()
        if s1 is not None and not u1:
            r1 -= s1(t, r1, temp, cue) if ready else a1()
        if s2 is not None and not u2:
            r2 -= s2(t, r2, temp, cue) if ready else a2()
        return r0, r1, r2

    def inline_lines(self, flags: list[str]) -> tuple[list[str], dict[str, Any]]:
        """The per-frame work of :meth:`__call__` as statements for the generated raw-frame handler
        (:func:`canical.bus.frame_handler.generate_raw_handler`), on its rates ``r0``..``r2``;
        ``flags[k]`` is ``"True"`` where axis ``k`` is uncalibrated in that handler's sets.

        The same steps on the same values in the same order as the call, without the call: the
        inputs are read once, each tracked axis's step is called straight. Only for the trackers
        of now: the handler is made anew with each generation of sets."""
        time_name, temp_name, cue_name = self._names
        names: dict[str, Any] = {"TRK": self, "NAN": NAN}
        if time_name is None:  # time since the first frame of this run
            lines = ["    trk_t = TRK.t0", "    if trk_t is None:", "        trk_t = TRK.t0 = stamp",
                     "    trk_t = stamp - trk_t"]
        else:
            lines = [f"    trk_t = values.get({time_name!r}, NAN)"]
        ready = ["trk_t == trk_t"]
        temp = "NAN" if temp_name is None else f"values.get({temp_name!r}, NAN)"
        lines.append(f"    trk_temp = {temp}")
        if temp_name is not None:
            ready.append("trk_temp == trk_temp")
        lines.append("    trk_cue = None" if cue_name is None else f"    trk_cue = values.get({cue_name!r})")
        if cue_name is not None:
            ready.append("trk_cue is not None")
        if self._joint is not None:
            if flags[0] == "True":
                return [], {}
            names.update(TRK_STEP3=self._joint.step, TRK_APPLIED3=self._joint.applied)
            return [*lines, f"    if {' and '.join(ready)}:",
                    "        b0, b1, b2 = TRK_STEP3(trk_t, r0, r1, r2, trk_temp, trk_cue)",
                    "    else:", "        b0, b1, b2 = TRK_APPLIED3()",
                    "    r0, r1, r2 = r0 - b0, r1 - b1, r2 - b2"], names
        tracked = [k for k, (step, _) in enumerate(self._steps) if step is not None and flags[k] != "True"]
        if not tracked:
            return [], {}
        lines.append(f"    if {' and '.join(ready)}:")
        lines.extend(f"        r{k} -= TRK_STEP{k}(trk_t, r{k}, trk_temp, trk_cue)" for k in tracked)
        lines.append("    else:")
        lines.extend(f"        r{k} -= TRK_APPLIED{k}()" for k in tracked)
        for k in tracked:
            names[f"TRK_STEP{k}"], names[f"TRK_APPLIED{k}"] = self._steps[k]
        return lines, names

    # -- between frames ------------------------------------------------------------------------
    def _sync(self) -> None:
        """The trackers brought up to date with their per-frame steps (before reading them)."""
        for fast in self._fast:
            if fast is not None:
                fast.sync()
        if self._joint is not None:
            self._joint.sync()

    def _updates(self) -> int:
        return sum(s.updates for t in self.trackers if t is not None for s in t.learned)

    def log_events(self) -> None:
        """Log each standstill decision, and hand it and each power-on to the field log."""
        measured = self.config.temperature_input is not None  # else the reference's, not a reading
        self._sync()
        for tracker in self.trackers:
            if tracker is None:
                continue
            for event in tracker.events:
                report = log.info if event.decision == "adopted" else log.warning
                report("bias %s", event.line(tracker.axes, temperature=measured))
            if self.field_log is not None:
                self.field_log.take(tracker, temperature=measured)
            tracker.events.clear()
            tracker.taken.clear()
            tracker.power_ons.clear()

    def finish(self) -> None:
        """The daemon stops: a standstill under way ends here (as at the end of a replayed drive)."""
        self._sync()
        for tracker in self.trackers:
            if tracker is not None:
                tracker.finish()

    def flush(self) -> None:
        """The field log's records since the last status period, written as a closed segment."""
        if self.field_log is not None:
            self.field_log.flush()

    def status_text(self) -> str:
        self._sync()
        return "; ".join(s.text() for t in self.trackers if t is not None for s in t.status())

    def save(self) -> None:
        """Write the learned state if it changed (atomically); a failure is logged, not fatal."""
        if self.config.state_file is None or self.set_id is None or self._updates() == self._saved_updates:
            return
        self._sync()
        learned = ([*self.trackers[0].learned] if self._joint is not None and self.trackers[0] is not None
                   else [t.learned[0] if t is not None else None for t in self.trackers])
        if any(s is None for s in learned):  # an uncalibrated axis: keep a fresh state in its place
            from canical.tracking.estimate import AxisBias

            learned = [s if s is not None else AxisBias() for s in learned]
        try:
            state_file.save(self.config.state_file, self.set_id, self.axes, learned)  # type: ignore[arg-type]
        except OSError as exc:
            log.warning("bias state %s: cannot write (%s)", self.config.state_file, exc)
            return
        self._saved_updates = self._updates()

    def status_pages(self) -> list[dict[str, Any]]:
        """Per tracked axis: learned bias, uncertainty, age, updates (for a status page or a test)."""
        self._sync()
        return [{"axis": s.axis, "bias_dps": s.bias_dps, "sigma_dps": s.sigma_dps, "age_s": s.age_s,
                 "updates": s.updates} for t in self.trackers if t is not None for s in t.status()]

    def frame_pages(self) -> list[dict[str, float]]:
        """Status frame page 3, one per tracked axis (signal name → value in its unit)."""
        return [{"BiasAxis": AXIS_CODES[p["axis"]], "BiasLearned": p["bias_dps"], "BiasSigma": p["sigma_dps"],
                 "BiasUpdates": min(p["updates"], 4095),
                 "BiasAge": 65535 if not math.isfinite(p["age_s"]) else min(round(p["age_s"]), 65535)}
                for p in self.status_pages()]
