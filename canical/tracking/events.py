"""What the tracker did at each standstill, as named records a log line or a report shows.

Why records and not log text: the daemon logs them, the offline report tabulates and plots
them, and the tests count them; all read the same fields.
"""

from __future__ import annotations

from dataclasses import dataclass

ADOPTED = "adopted"
REFUSED = "refused"


@dataclass(frozen=True)
class StandstillEvent:
    """One run of still windows: what it measured and whether the bias was learned from it."""

    start_s: float  # time since power-on of the run's first still window
    end_s: float  # ... and of its last
    power_cycle: int  # counts power-ons seen by this tracker, from 0
    decision: str  # ADOPTED or REFUSED
    reason: str  # why: what was learned, or why nothing was
    windows_used: int
    windows_refused: int
    mean_dps: tuple[float, ...]  # per axis, over the used windows (the refused ones if none used)
    uncertainty_dps: tuple[float, ...]  # 1σ of that mean
    temp_c: float
    bias_after_dps: tuple[float, ...]  # the learned bias at temp_c once the run was taken in

    def line(self, axes: tuple[str, ...], *, temperature: bool = True) -> str:
        """One log line: when, what, the decision and why; ``temperature`` False: none was
        recorded (``temp_c`` is then the tracker's reference, not a measurement: not shown)."""
        means = ", ".join(f"{a} {m:+.4f}±{u:.4f}" for a, m, u in
                          zip(axes, self.mean_dps, self.uncertainty_dps, strict=True))
        where = f"at {self.temp_c:.1f} °C" if temperature else "temperature not recorded"
        return (f"standstill {self.start_s:.1f}-{self.end_s:.1f} s (power-on {self.power_cycle}) {where}: "
                f"{self.decision}, {self.reason}; measured {means} deg/s")


@dataclass(frozen=True)
class PowerOnEvent:
    """A power-on the tracker saw (its start, or time since power-on going back): the turn-on bias
    is new, so the offset starts from what was learned with the turn-on spread as its 1σ."""

    power_cycle: int
    bias_dps: tuple[float, ...]  # per axis, the learned bias at the reference temperature
    sigma_dps: tuple[float, ...]  # its 1σ: the turn-on spread (and the slope's at the reference)
    previous_end_s: float = float("nan")  # the last time since power-on of the power-on before


@dataclass(frozen=True)
class TakenWindow:
    """One still window the bias was learned from, and what it changed (per axis, at its temperature)."""

    start_s: float
    end_s: float
    power_cycle: int
    temp_c: float
    mean_dps: tuple[float, ...]
    before_dps: tuple[float, ...]
    after_dps: tuple[float, ...]
