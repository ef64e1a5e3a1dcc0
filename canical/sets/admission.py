"""Whether a coefficient set may run on a given IMU: the checks the tool and the device share.

A valid set (CRC and fields) can still be wrong for the device it is sent to.
Both ``canical push`` (before it writes anything) and the device (when asked to
activate a bank) refuse a set when:

* its ``sensor.id`` is not this device's serial number as decimal text
  (:func:`canical.frames.imu_dictionary.sensor_id_for_serial`): a calibration of
  another sensor;
* its axis is not the axis of the bank it sits in;
* its span does not cover the sensor's rated range: the rates at the two edges
  of ``model.span_raw``, through the set's own rate model, must reach at least
  −R and +R, R the device's rated range for the axis (object "Rated range").
  A narrower set would extrapolate over part of the range the sensor is sold
  for; such a set needs a wider turntable session, not a download;
* its terms do not fit the device's evaluator (``firmware/canical_eval.c``): more
  terms than it holds (:data:`MAX_TERMS`, ``CE_MAX_TERMS``), more spline terms than its
  slots (:data:`MAX_SPLINE_TERMS`, ``CE_MAX_SPLINES``), or a spline knot or piece beyond
  float32 range (the device holds them as float32);
* its bank content (the set's canonical JSON) is longer than the device's banks hold
  (object "Coefficient bank capacity", when the device's limits say it): a spline's
  knots and pieces are a few kilobytes.

Pure: no bus, no files.
"""

from __future__ import annotations

from dataclasses import dataclass
from itertools import pairwise

import numpy as np

from canical.frames.imu_dictionary import sensor_id_for_serial
from canical.sets.coefficient_file import canonical_bytes
from canical.sets.coefficients import CoefficientSet
from canical.sets.term_params import Curve

#: Effect terms the device's evaluator holds in one set (``CE_MAX_TERMS`` of canical_eval.h).
MAX_TERMS = 16
#: Spline terms the device's evaluator holds in one set (``CE_MAX_SPLINES`` of canical_eval.h;
#: each of up to MAX_SPLINE_KNOTS knots, ``CE_MAX_SPLINE_KNOTS``). A test compares them.
MAX_SPLINE_TERMS = 4
#: The largest float32: a spline's knots and pieces are held as float32 on the device.
FLOAT32_MAX = float(np.finfo(np.float32).max)


@dataclass(frozen=True)
class DeviceLimits:
    """What a device states about itself that a set must fit."""

    serial: int
    rated_range_dps: dict[str, float]
    #: Bytes one coefficient bank holds (None: not stated, not checked).
    bank_capacity: int | None = None


def raw_units_problem(set_units: str, signal_units: str | None) -> str | None:
    """Why a set may not correct a raw signal in ``signal_units`` (None: it may).

    A set maps raw values in one unit to deg/s; fed another unit's numbers it corrects them as if
    they were its own (5.49 deg/s became -0.216). A signal whose unit is not stated (a DBC signal
    without a unit, a CSV without a ``# raw_units:`` line) cannot be checked, so it passes; a set
    that says ``counts`` is for counts, as its file says, and is refused on a signal in deg/s.
    """
    if not signal_units or set_units == signal_units:
        return None
    return (f"set is for raw values in {set_units}, the signal is in {signal_units}: calibrate from "
            f"this signal (a CAN log of it, or a CSV with the line '# raw_units: {signal_units}')")


def span_rates(cset: CoefficientSet) -> tuple[float, float]:
    """Lowest and highest rate (deg/s) the set's model gives inside its span."""
    lo, hi = cset.span_raw
    rates, _ = cset.rate_model().evaluate(np.array([lo - cset.v0, hi - cset.v0]))
    return float(np.min(rates)), float(np.max(rates))


def evaluator_problem(cset: CoefficientSet) -> str | None:
    """Why the device's evaluator cannot hold the set's terms though canical evaluates them
    (None: it can). Why here: the device would refuse the bank (``CE_ERR_LIMIT``) after the
    download; ``canical push`` says so before writing anything."""
    if len(cset.terms) > MAX_TERMS:
        return f"{len(cset.terms)} terms, the device's evaluator holds {MAX_TERMS} per set (CE_MAX_TERMS)"
    splines = [(i, t.params) for i, t in enumerate(cset.terms) if isinstance(t.params, Curve)]
    if len(splines) > MAX_SPLINE_TERMS:
        return (f"{len(splines)} spline terms, the device's evaluator holds {MAX_SPLINE_TERMS} per set "
                f"(CE_MAX_SPLINES)")
    for i, curve in splines:
        knots = [float(k) for k in curve.knots]
        pieces = [float(a) for row in curve.pieces for a in row]
        values = [*knots, *(b - a for a, b in pairwise(knots)), *pieces]
        if values and max(abs(v) for v in values) > FLOAT32_MAX:
            return (f"terms[{i}]: a spline knot, knot spacing or piece beyond float32 range, "
                    "which the device holds")
    return None


def admission_problem(cset: CoefficientSet, axis: str, limits: DeviceLimits) -> str | None:
    """Why ``cset`` may not run as ``axis`` on this device, or None when it may."""
    expected = sensor_id_for_serial(limits.serial)
    if cset.sensor_id != expected:
        return f"set is for sensor {cset.sensor_id}, this device is serial {expected}"
    if cset.axis != axis:
        return f"set is for axis {cset.axis}, not axis {axis}"
    rated = limits.rated_range_dps.get(axis)
    if rated is not None and rated > 0:
        low, high = span_rates(cset)
        if low > -rated or high < rated:
            return (
                f"axis {axis}: set spans {low:+.1f}..{high:+.1f} deg/s, "
                f"does not cover the rated range ±{rated:g} deg/s"
            )
    problem = evaluator_problem(cset)
    if problem is not None:
        return f"axis {axis}: {problem}"
    if limits.bank_capacity is not None:
        size = len(canonical_bytes(cset.to_dict()))
        if size > limits.bank_capacity:
            return (f"axis {axis}: set is {size} bytes, the device's coefficient banks hold "
                    f"{limits.bank_capacity} (fewer spline knots or terms would fit)")
    return None
