"""What stays unexplained after the closed loop: the residual against the session's noise floor.

The loop can only add what its candidates represent. When the sensor has an
effect in another form (or follows a variable nobody recorded), the held-out
residual stays well above what noise alone leaves, and a calibration shipped
as if it were explained would surprise the field. So, after the loop:

* the **noise floor** is measured from the session itself: the scatter between
  successive blocks of the same plateau (same rate, a few seconds apart) of the
  final model's residual, which holds the sensor's noise at the block length and
  neither what the model explains (an effect that changes within a plateau) nor
  what it lacks that changes slowly; robust (median-based), so a few transients
  do not raise it;
* the held-out residual is compared with it; above ``UNEXPLAINED_RATIO`` times
  the floor the residual is called *unexplained*. The comparison uses a robust
  rms (from the median of the squared errors): a structured residual spreads over
  most blocks and shows in it, while a fold whose fit broke down on a few
  plateaus (a segment left without points) does not pass for an effect;
* the residual is correlated with every candidate variable (each channel's
  level, derivative, lag, direction of change, time, direction of approach...)
  and the best-correlated are named: where to look next.

Pure functions on the loop's blocks: no I/O.
"""

from __future__ import annotations

from dataclasses import asdict, dataclass
from typing import Any

import numpy as np

from canical.closed_loop.blocks import Blocks
from canical.closed_loop.candidates import Candidate, feature
from canical.models.robust_stats import mad_sigma
from canical.sets.term_kinds import CHANNEL_DERIVATIVE, CHANNEL_LAG, ChannelTransformSpline
from canical.sets.term_params import Lag
from canical.sets.terms import Term

# Clean simulated sensors (white noise, or with bias instability and rate random
# walk) leave 1.0-1.4x the floor on held-out plateaus; an unexplained effect the
# size of the noise doubles it.
UNEXPLAINED_RATIO = 2.0
TOP_CORRELATED = 3
WEAK_R = 0.3  # below this, no candidate variable follows the residual


def block_noise_floor(blocks: Blocks, fitted_residual: np.ndarray) -> float:
    """Rms noise of one block mean in deg/s, from successive blocks of the same plateau.

    ``fitted_residual`` is the final model's residual at every block (deg/s). For
    two successive blocks of one plateau its difference holds twice the block
    noise; 1.4826·MAD/√2 estimates that standard deviation robustly.
    """
    same = blocks.plateau[1:] == blocks.plateau[:-1]
    if not np.any(same):  # one block per plateau: the blocks' own standard errors
        return float(np.median(blocks.points.dv_sem)) / _sensitivity(blocks)
    d = np.diff(fitted_residual)[same]
    return mad_sigma(d) / np.sqrt(2.0)


def _sensitivity(blocks: Blocks) -> float:
    p = blocks.points
    return abs(float(np.polyfit(p.rate, p.dv, 1)[0])) or 1.0


def candidate_variables(candidates: list[Candidate], blocks: Blocks) -> dict[str, np.ndarray]:
    """Each candidate's variable at the blocks (its first term's feature; a smooth candidate's, its
    channel, or the lag or rate of change it is a function of: its first term is one basis
    function of it), and time since power-on."""
    out = {"time since power-on": blocks.time_s}
    for cand in candidates:
        first = cand.terms[0]
        if isinstance(first.spec, ChannelTransformSpline) and isinstance(first.params, Lag):
            lagged = CHANNEL_DERIVATIVE if first.spec.derivative else CHANNEL_LAG
            out[cand.name] = feature(Term.of(lagged, "bias", 0.0, channel=first.params.channel,
                                             tau_s=first.params.tau_s), blocks)
        elif first.spec.needs_spline and cand.channel is not None:
            out[cand.name] = blocks.aux[cand.channel]
        else:
            out[cand.name] = feature(first, blocks)
    return out


def correlations(residual: np.ndarray, variables: dict[str, np.ndarray]) -> list[tuple[str, float]]:
    """|Pearson r| of the residual with each variable (0 for a constant one), best first."""
    out = []
    held = np.isfinite(residual)  # blocks without a held-out error do not count
    residual = residual[held]
    for name, x in ((n, v[held]) for n, v in variables.items()):
        sx, sr = float(np.std(x)), float(np.std(residual))
        r = 0.0 if sx == 0 or sr == 0 else float(np.corrcoef(x, residual)[0, 1])
        out.append((name, abs(r) if np.isfinite(r) else 0.0))
    return sorted(out, key=lambda kv: -kv[1])


def robust_rms(e: np.ndarray) -> float:
    """The rms a Gaussian residual with the same median square would have (0.4549: χ²₁ median)."""
    return float(np.sqrt(np.median(np.asarray(e) ** 2) / 0.4549))


@dataclass(frozen=True)
class Correlate:
    """A candidate variable and how closely the residual follows it."""

    variable: str
    abs_r: float


@dataclass(frozen=True)
class Unexplained:
    """The report's ``unexplained`` section: residual rms, floor, ratio, verdict, best correlates."""

    held_out_rms_dps: float
    held_out_robust_rms_dps: float
    noise_floor_dps: float
    ratio: float
    limit_ratio: float
    unexplained: bool
    noise_floor_method: str
    correlates: tuple[Correlate, ...]

    def to_dict(self) -> dict[str, Any]:
        return asdict(self)


def account(
    residual: np.ndarray,
    fitted_residual: np.ndarray,
    blocks: Blocks,
    candidates: list[Candidate],
    ratio_limit: float = UNEXPLAINED_RATIO,
) -> Unexplained:
    """The report's ``unexplained`` section: residual rms, floor, ratio, verdict, best correlates.

    ``residual``: held-out errors after the loop; ``fitted_residual``: the final
    model's in-sample residual (for the floor), both deg/s at every block.
    """
    floor = float(block_noise_floor(blocks, fitted_residual))
    held = np.isfinite(residual)  # the extreme rates have no held-out error
    residual = residual[held]
    rms = float(np.sqrt(np.mean(residual**2)))
    robust = robust_rms(residual)
    ratio = float(robust / floor) if floor > 0 else float("inf")
    ranked = correlations(residual, {k: v[held] for k, v in candidate_variables(candidates, blocks).items()})
    return Unexplained(
        held_out_rms_dps=rms,
        held_out_robust_rms_dps=robust,
        noise_floor_dps=floor,
        ratio=ratio,
        limit_ratio=ratio_limit,
        unexplained=bool(ratio > ratio_limit),
        noise_floor_method=f"scatter between successive {blocks.label} of one plateau (median-based)",
        correlates=tuple(Correlate(n, float(r)) for n, r in ranked[:TOP_CORRELATED]),
    )


def one_line(section: Unexplained) -> str:
    """What the CLI prints: ``unexplained: 0.07 deg/s rms, 18× the noise floor (...)``."""
    rms, floor, ratio = section.held_out_robust_rms_dps, section.noise_floor_dps, section.ratio
    if not section.unexplained:
        return f"residual   {rms:.4f} deg/s rms, {ratio:.1f}× the noise floor {floor:.4f}: explained"
    return (f"unexplained: {rms:.3g} deg/s rms, {ratio:.0f}× the noise floor {floor:.4f} deg/s; "
            + where_to_look(section))


def where_to_look(section: Unexplained) -> str:
    """The best-correlated candidate variables, or that none follows the residual."""
    best = ", ".join(f"{c.variable} (|r| {c.abs_r:.2f})" for c in section.correlates)
    if not section.correlates or section.correlates[0].abs_r < WEAK_R:
        return f"no recorded variable follows it (best: {best}): look for one that was not recorded"
    return f"correlates best with {best}"
