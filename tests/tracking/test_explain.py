"""What the learned bias follows: the simplest model that explains the windows' means."""

from __future__ import annotations

import numpy as np

from canical.tracking.events import TakenWindow
from canical.tracking.explain import OFFSETS, chosen, explain, too_little_evidence


def windows(bias, seed: int = 0) -> list[TakenWindow]:
    """Windows over two power-ons, the cabin warming while time since power-on runs."""
    rng = np.random.default_rng(seed)
    out = []
    for cycle, (t0_c, offset) in enumerate(((20.0, 0.3), (35.0, -0.1))):
        for k in range(12):
            t = 30.0 * k + 5.0
            temp = t0_c + 10.0 * np.sin(k) ** 2  # temperature not a function of time
            mean = offset + bias(temp, t) + 0.002 * rng.standard_normal()
            out.append(TakenWindow(t, t + 1.0, cycle, temp, (mean,), (0.0,), (0.0,)))
    return out


def test_a_temperature_drift_is_traced_to_temperature() -> None:
    models = explain(windows(lambda temp, t: 0.012 * (temp - 20.0)))
    pick = chosen(models)
    assert pick.model == f"{OFFSETS} + temperature"
    assert abs(pick.terms["temperature (deg/s/°C)"] - 0.012) < 0.001
    assert pick.rms_dps < 0.005 < next(m.rms_dps for m in models if m.model == OFFSETS)


def test_a_drift_with_time_since_power_on_is_traced_to_time() -> None:
    pick = chosen(explain(windows(lambda temp, t: 2e-4 * t)))
    assert pick.model == f"{OFFSETS} + time since power-on"


def test_too_few_windows_explain_nothing() -> None:
    assert explain(windows(lambda temp, t: 0.0)[:2]) == []


def test_three_windows_over_four_seconds_are_too_little_evidence() -> None:
    """A drive's 3 windows over 4 s fit an offset and a time term exactly: no conclusion from them."""
    few = [TakenWindow(t, t + 1.0, 0, 25.0, (0.3 + 0.01 * t,), (0.0,), (0.0,)) for t in (10.0, 12.0, 14.0)]
    assert explain(few) == []
    assert too_little_evidence(few) == ("3 window(s) over 4 s since power-on; at least 10 over 60 s "
                                        "are needed")
    assert too_little_evidence(windows(lambda temp, t: 0.0)) is None
