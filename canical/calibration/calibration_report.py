"""The calibration report as one record: built once by the pipeline, read by name everywhere.

:func:`canical.calibration.pipeline.calibrate` builds a :class:`CalibrationReport`; report.json is its
:meth:`~CalibrationReport.to_dict`, report.md (:mod:`canical.report.markdown`) and the CLI's
summary (:mod:`canical.commands.calibrate`) read its fields. One tree, so a field added or
renamed is one change here that mypy follows to every reader, where a string-keyed dict
let each of them spell its keys on its own.

The JSON form is the file format users keep: ``to_dict`` gives the same keys in the same
order as before the record existed. No numpy at import: the CLI's ``--help`` stays fast.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass, replace
from typing import TYPE_CHECKING, Any

if TYPE_CHECKING:
    from canical.calibrate.allan import NoiseAnalysis, NoiseSkipped
    from canical.calibrate.plateaus import PlateauFinding
    from canical.closed_loop.findings import Confound, Effect, LoopStep, RoundRow
    from canical.closed_loop.unexplained import Unexplained
    from canical.sessions.reference_clock import ReferenceClock

RATE_MODEL_VALIDATION = "leave-rates-out cross-validation"
UNTESTABLE_WHY = ("follows the table rate in this session; visit the rates in random order "
                  "or sweep up and down to test it")


@dataclass(frozen=True)
class SampleCounts:
    """Where the session's samples went: plateaus (used), ramps (transition), settling."""

    total: int
    used: int
    transition: int
    settling: int


@dataclass(frozen=True)
class ErrorStats:
    """Rms and largest error, deg/s."""

    rms_dps: float
    max_dps: float


@dataclass(frozen=True)
class LeftOutPlateau:
    """A plateau found but not fitted (its output at a rail), where it is and why."""

    index: int
    rate_dps: float
    start_s: float
    stop_s: float
    why: str

    def label(self) -> str:
        return f"{self.rate_dps:g} deg/s at {self.start_s:.1f}-{self.stop_s:.1f} s ({self.why})"


@dataclass(frozen=True)
class SegmentPoint:
    """A segment point of the rate model, where the residual of a smaller model peaked."""

    rate_dps: float
    raw: float
    prominence_dps: float
    source: str


@dataclass(frozen=True)
class SizeCandidate:
    """One base-model size the selection tried, with its held-out error."""

    segments: int
    order: int
    coefficients: int
    held_out_rms_dps: float
    held_out_max_dps: float
    monotone: bool


@dataclass(frozen=True)
class NoiseLevels:
    """The rate noise of one sample and of one plateau mean, deg/s."""

    per_sample_dps: float
    plateau_mean_dps: float


@dataclass(frozen=True)
class Untestable:
    """A candidate the session cannot test: it follows the table rate."""

    candidate: str
    r2_with_table_rate: float
    why: str = UNTESTABLE_WHY


@dataclass(frozen=True)
class LoopSection:
    """The closed loop's before and after on held-out plateaus, and how it got there."""

    held_out_rms_before_dps: float
    held_out_rms_after_dps: float
    held_out_max_before_dps: float
    held_out_max_after_dps: float
    method: str
    #: Seconds per block the loop fitted: BLOCK_S, longer on sessions of hours (MAX_BLOCKS).
    block_s: float
    final_spec: str
    capacity_changes: tuple[str, ...]
    untestable: tuple[Untestable, ...]
    rounds: tuple[tuple[RoundRow, ...], ...]
    steps: tuple[LoopStep, ...]
    # The extreme rates train every fold: judged apart, in sample (None: no such blocks).
    extreme_rates_in_sample_rms_dps: float | None = None
    # Session times (s) the sensor's bias jumped at: taken out where a channel's form met the
    # session's drift, and not in the set (a jump is the session's, not the sensor's).
    bias_jumps_s: tuple[float, ...] = ()

    @property
    def blocks_label(self) -> str:
        """What the figures were measured on: ``2 s blocks``."""
        from canical.closed_loop.blocks import block_label

        return block_label(self.block_s)

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


@dataclass(frozen=True)
class Written:
    """What the coefficient file holds: the loop's final model, or the rate model alone."""

    spec: str
    effect_terms: int


@dataclass(frozen=True)
class CalibrationReport:
    """Everything a calibration tells its user; see the module docstring."""

    model: str
    spec: str
    segments: int
    order: int
    smoothness: int | None  # None: not a segmented-inverse model
    v0: float
    samples: SampleCounts
    plateaus: int
    plateau_finding: PlateauFinding
    saturated_rates_dps: tuple[float, ...]
    rates: int
    segment_points: tuple[SegmentPoint, ...]
    training: ErrorStats
    held_out: ErrorStats  # leave-rates-out cross-validation on plateau means
    noise: NoiseLevels
    candidates: tuple[SizeCandidate, ...]
    allan: NoiseAnalysis | NoiseSkipped | None  # None: not analysed yet (the base report)
    written: Written
    max_jump_at_segment_points_dps: float | None = None  # None: a model without jumps
    effects: tuple[Effect, ...] = ()
    confounded: tuple[Confound, ...] = ()
    closed_loop: LoopSection | None = None  # None: the loop did not run
    loop_skipped: str | None = None  # why the loop was asked for and could not run
    unexplained: Unexplained | None = None  # with the closed loop only
    session: str | None = None  # the input and output paths, when the CLI knows them
    coefficients: str | None = None
    left_out_plateaus: tuple[LeftOutPlateau, ...] = ()
    reference_clock: ReferenceClock | None = None  # a table file aligned to the log (the CLI's)
    read_as_means: str | None = None  # "N rows read as M means of k": a session too long to hold

    def with_paths(self, session: str, coefficients: str) -> CalibrationReport:
        return replace(self, session=session, coefficients=coefficients)

    def with_reference_clock(self, clock: ReferenceClock | None) -> CalibrationReport:
        return replace(self, reference_clock=clock)

    def written_model(self) -> str:
        """The model in the coefficient file: the loop's final one, with its effect terms."""
        n = self.written.effect_terms
        names = ", ".join(e.name for e in self.effects)
        return self.written.spec + (f" + {n} effect term{'s' * (n != 1)} ({names})" if n else "")

    def to_dict(self) -> dict[str, Any]:
        """The report.json form (keys in the order the file has always had)."""
        out: dict[str, Any] = {}
        if self.session is not None:
            out["session"] = self.session
        if self.coefficients is not None:
            out["coefficients"] = self.coefficients
        if self.reference_clock is not None:
            out["reference_clock"] = self.reference_clock.to_dict()
        out |= {
            "model": self.model,
            "spec": self.spec,
            "segments": self.segments,
            "order": self.order,
            "smoothness": self.smoothness,
            "v0": self.v0,
            "samples": asdict(self.samples),
            **({"read_as_means": self.read_as_means} if self.read_as_means is not None else {}),
            "plateaus": self.plateaus,
            "plateau_finding": self.plateau_finding.to_dict(),
            "saturated_rates_dps": list(self.saturated_rates_dps),
            "left_out_plateaus": [asdict(p) for p in self.left_out_plateaus],
            "rates": self.rates,
            "segment_points": [asdict(p) for p in self.segment_points],
            "training": asdict(self.training),
            "held_out": {**asdict(self.held_out), "method": RATE_MODEL_VALIDATION},
            "noise": asdict(self.noise),
            "candidates": [asdict(c) for c in self.candidates],
            "effects": [e.to_dict() for e in self.effects],
        }
        if self.max_jump_at_segment_points_dps is not None:
            out["max_jump_at_segment_points_dps"] = self.max_jump_at_segment_points_dps
        out["allan"] = self.allan.to_dict() if self.allan is not None else {}
        if self.closed_loop is not None:
            out["confounded"] = [c.to_dict() for c in self.confounded]
            out["closed_loop"] = self.closed_loop.to_dict()
        elif self.loop_skipped is not None:
            out["closed_loop"] = {"skipped": self.loop_skipped}
        if self.unexplained is not None:
            out["unexplained"] = self.unexplained.to_dict()
        out["written"] = asdict(self.written)
        return out
