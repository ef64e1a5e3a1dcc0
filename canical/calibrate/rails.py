"""Which plateaus the sensor spent at a rail of its output: from the signal's definition, never its values.

A plateau where the output is clipped says nothing about the scale factor at its rate
(every rate beyond the rail reads the same), so it must not be fitted. Where the rail is
has to come from what the output *can* be, not from what it happened to be:

* **A known rail** (the raw signal's range in the DBC, from its bit width, scale and offset
  and any declared minimum/maximum; or a declared ``--rail LO,HI`` / ``# rail: LO,HI``):
  a plateau is at the rail when at least ``MIN_AT_RAIL`` of its samples are at or beyond a
  limit (within half the signal's resolution).
* **No known rail**: a recurring extreme value is *not* evidence. A sensor quantised to
  0.1 deg/s repeats its most extreme value in a few percent of a plateau's samples, and a
  low-pass-filtered one repeats it too; both used to lose their outermost plateaus. Only a
  **pinned** output is taken for a rail: at least ``PINNED_SHARE`` (90 %) of a plateau's
  samples at the session's extreme value, *and* either its spread collapsed (below
  ``COLLAPSED_SPREAD`` of the other plateaus' typical spread: noise spreads a plateau over
  several values, a converter at its rail outputs one whatever the noise) or a plateau at a
  different table rate is pinned to the same value (two rates reading one value is clipping
  even for a sensor whose noise is below one step, where every plateau has one value).
  Once pinned plateaus show a rail's value, plateaus with ``MIN_AT_RAIL`` of their samples
  at that value are left out as at a known rail. A plateau only partly at a rail no plateau
  is pinned to is kept: declare the rail to have it left out.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from canical.calibrate.plateaus import Plateaus, plateau_means

MIN_AT_RAIL = 0.01  # share of a plateau's samples at a known rail that leaves it out
PINNED_SHARE = 0.9  # share at one extreme value for a pinned plateau (no rail known)
COLLAPSED_SPREAD = 0.25  # ...whose spread is below this share of the typical plateau's
SAME_RATE_DPS = 0.1  # plateaus closer than this are at the same table rate


@dataclass(frozen=True)
class RailLimits:
    """The raw signal's limits and resolution, and where they come from (for the user)."""

    low: float
    high: float
    source: str
    resolution: float = 0.0


@dataclass(frozen=True)
class RailCheck:
    """Per plateau: whether it is left out as at a rail, and why (one phrase each)."""

    left_out: np.ndarray  # bool per plateau
    why: tuple[str, ...]  # per plateau; "" where kept

    @property
    def count(self) -> int:
        return int(np.count_nonzero(self.left_out))


def rail_plateaus(raw: np.ndarray, plateaus: Plateaus, rail: RailLimits | None, *,
                  lowest: np.ndarray | None = None, highest: np.ndarray | None = None) -> RailCheck:
    """The plateaus at a rail: by the known limits, or (none known) only where the output is pinned.

    ``lowest``/``highest``: per row of a session read as means of several samples, the lowest
    and highest sample behind it (the means themselves rarely reach a rail): a row is at a
    rail when any of its samples is, so shares count rows that touch it.
    """
    x = np.asarray(raw, dtype=float)
    low_x = x if lowest is None else np.asarray(lowest, dtype=float)
    high_x = x if highest is None else np.asarray(highest, dtype=float)
    if plateaus.count == 0:
        return RailCheck(np.zeros(0, dtype=bool), ())
    if rail is not None:
        return _at_known_rail(low_x, high_x, plateaus, rail)
    return _pinned(x, low_x, high_x, plateaus)


def _at_known_rail(low_x: np.ndarray, high_x: np.ndarray, plateaus: Plateaus, rail: RailLimits) -> RailCheck:
    tol = rail.resolution / 2 + 1e-9 * max(abs(rail.low), abs(rail.high), 1.0)
    high = plateau_means((high_x >= rail.high - tol).astype(float), plateaus)
    low = plateau_means((low_x <= rail.low + tol).astype(float), plateaus)
    out = (high >= MIN_AT_RAIL) | (low >= MIN_AT_RAIL)
    why = tuple(
        f"{100 * max(h, lo):.0f} % of its samples at the rail "
        f"{rail.high if h >= lo else rail.low:g} ({rail.source})" if o else ""
        for o, h, lo in zip(out, high, low, strict=True))
    return RailCheck(out, why)


def _pinned(x: np.ndarray, low_x: np.ndarray, high_x: np.ndarray, plateaus: Plateaus) -> RailCheck:
    hi, lo = float(np.max(high_x)), float(np.min(low_x))
    share_hi = plateau_means((high_x == hi).astype(float), plateaus)
    share_lo = plateau_means((low_x == lo).astype(float), plateaus)
    value = np.where(share_hi >= share_lo, hi, lo)
    share = np.maximum(share_hi, share_lo)
    spread = np.array([np.std(x[a:b]) for a, b in zip(plateaus.start, plateaus.stop, strict=True)])
    candidate = share >= PINNED_SHARE
    others = spread[~candidate]
    typical = float(np.median(others)) if others.size else 0.0
    collapsed = spread < COLLAPSED_SPREAD * typical
    rates = plateaus.rate_dps
    apart = np.maximum(SAME_RATE_DPS, 4 * plateaus.rate_uncertainty())  # repeated sweeps: the same rate
    shared = np.array([
        bool(np.any(candidate & (value == value[i]) & (np.abs(rates - rates[i]) > apart[i])))
        for i in range(rates.size)
    ])
    pinned = candidate & (collapsed | shared)
    # A value pinned plateaus show is a rail: others partly at it are clipped too.
    seen = np.isin(np.array([hi, lo]), value[pinned])
    partly = ~pinned & (((share_hi >= MIN_AT_RAIL) & seen[0]) | ((share_lo >= MIN_AT_RAIL) & seen[1]))
    partly_share = np.where(seen[0], share_hi, 0.0) + np.where(seen[1], share_lo, 0.0)
    why = tuple(
        (f"pinned: {100 * s:.0f} % of its samples at {v:g}, the session's extreme"
         + (", as at another table rate" if sh else ", its noise gone")) if p else
        (f"{100 * ps:.0f} % of its samples at {hi if sh_hi >= sh_lo else lo:g}, "
         "where other plateaus are pinned") if q else ""
        for p, q, s, v, sh, ps, sh_hi, sh_lo in zip(pinned, partly, share, value, shared, partly_share,
                                                   share_hi, share_lo, strict=True))
    return RailCheck(pinned | partly, why)
