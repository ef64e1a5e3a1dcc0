"""Whether a coefficient set may run on a given IMU: the checks the tool and the device share.

A valid set (CRC and fields) can still be wrong for the device it is sent to.
Both ``canical push`` (before it writes anything) and the device (when asked to
activate a bank) refuse a set when:

* its ``sensor.id`` is not this device's serial number as decimal text
  (:func:`canical.imu_dictionary.sensor_id_for_serial`): a calibration of
  another sensor;
* its axis is not the axis of the bank it sits in;
* its span does not cover the sensor's rated range: the rates at the two edges
  of ``model.span_raw``, through the set's own rate model, must reach at least
  −R and +R, R the device's rated range for the axis (object "Rated range").
  A narrower set would extrapolate over part of the range the sensor is sold
  for; such a set needs a wider turntable session, not a download.

Pure: no bus, no files.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from canical.imu_dictionary import sensor_id_for_serial
from canical.sets.coefficients import CoefficientSet


@dataclass(frozen=True)
class DeviceLimits:
    """What a device states about itself that a set must fit."""

    serial: int
    rated_range_dps: dict[str, float]


def span_rates(cset: CoefficientSet) -> tuple[float, float]:
    """Lowest and highest rate (deg/s) the set's model gives inside its span."""
    lo, hi = cset.span_raw
    rates, _ = cset.rate_model().evaluate(np.array([lo - cset.v0, hi - cset.v0]))
    return float(np.min(rates)), float(np.max(rates))


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
    return None
