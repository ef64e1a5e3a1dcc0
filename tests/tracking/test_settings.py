"""The daemon's bias_tracking: section: every key checked, one line naming the key."""

from __future__ import annotations

import math

import pytest

from canical.errors import CanicalError
from canical.tracking.settings import KEYS, parse_bias_tracking
from canical.tracking.tracker import AxisStatus


def fail(key: str, msg: str) -> CanicalError:
    return CanicalError(f"can0.yaml: {key}: {msg}")


def test_no_section_is_off() -> None:
    settings = parse_bias_tracking(None, fail)
    assert not settings.enabled and settings.cue_input is None and settings.temperature_input == "temp_c"


def test_a_full_section() -> None:
    settings = parse_bias_tracking({"enabled": True, "arw_deg_rt_h": 0.3, "window_s": 2, "bound_dps": 1.5,
                                    "cue": {"input": "speed", "below": 0.2}, "temperature": "cabin_c",
                                    "state_file": "bias.json"}, fail)
    assert settings.enabled and settings.cue_input == "speed" and settings.state_file == "bias.json"
    assert settings.temperature_input == "cabin_c"
    assert settings.tracker.cue_threshold == 0.2 and settings.tracker.window_s == 2.0
    assert settings.tracker.bound_dps == 1.5 and settings.tracker.arw_deg_rt_h == 0.3


@pytest.mark.parametrize(("section", "message"), [
    ([], "bias_tracking: must be a mapping"),
    ({"enabeld": True}, "bias_tracking.enabeld: unknown key (expected one of arw_deg_rt_h, bound_dps, cue"),
    ({"enabled": "yes"}, "bias_tracking.enabled: must be true or false"),
    ({"window_s": 0}, "bias_tracking.window_s: must be a positive number"),
    ({"bound_dps": math.nan}, "bias_tracking.bound_dps: must be a finite number"),
    ({"vibration_dps": -1}, "bias_tracking.vibration_dps: must be a non-negative number"),
    ({"cue": "speed"}, "bias_tracking.cue: must be a mapping"),
    ({"cue": {"input": 3}}, "bias_tracking.cue.input: must name an input"),
    ({"cue": {"input": "speed", "below": "low"}}, "bias_tracking.cue.below: must be a finite number"),
    ({"cue": {"input": "speed", "below": -0.1}}, "bias_tracking.cue.below: must be a positive number"),
    ({"cue": {"input": "speed", "above": 1}}, "bias_tracking.cue.above: unknown key"),
    ({"temperature": ""}, "bias_tracking.temperature: must name an input"),
    ({"state_file": 3}, "bias_tracking.state_file: must be a file path"),
])
def test_a_bad_key_is_one_line_naming_it(section, message: str) -> None:
    with pytest.raises(CanicalError) as info:
        parse_bias_tracking(section, fail)
    assert str(info.value).startswith(f"can0.yaml: {message}")
    assert "\n" not in str(info.value)


def test_every_documented_key_is_accepted() -> None:
    values = {"enabled": True, "cue": {"input": "speed", "below": 0.1}, "state_file": "s.json",
              "temperature": "temp_c"}
    section = {k.key: values.get(k.key, 0.5) for k in KEYS if "." not in k.key}
    assert parse_bias_tracking(section, fail).enabled


def test_a_status_line_says_bias_uncertainty_age_and_updates() -> None:
    line = AxisStatus("z", 0.4123, 0.0031, 0.41, 12.0, 158).text()
    assert line == "z bias +0.4123±0.0031 deg/s (applied +0.4100), 158 updates, last 12 s ago"
    assert "not yet this power-on" in AxisStatus("z", 0.0, 0.5, 0.0, math.nan, 0).text()


def test_the_sets_angle_random_walk_is_used_unless_given() -> None:
    """A standstill is told by each set's own measured noise; a configured figure overrides it."""
    base = parse_bias_tracking({"enabled": True}, fail)
    assert not base.arw_given
    assert base.tracker.for_set({"arw_deg_rt_h": 0.21}, arw_given=False).arw_deg_rt_h == 0.21
    assert base.tracker.for_set({}, arw_given=False).arw_deg_rt_h == base.tracker.arw_deg_rt_h
    assert base.tracker.for_set({"arw_deg_rt_h": -1.0}, arw_given=False) is base.tracker
    given = parse_bias_tracking({"enabled": True, "arw_deg_rt_h": 0.4}, fail)
    assert given.arw_given
    assert given.tracker.for_set({"arw_deg_rt_h": 0.21}, arw_given=True).arw_deg_rt_h == 0.4


def test_a_set_whose_slope_the_fleet_measured_narrows_the_slope_prior() -> None:
    """A proposed set (fit.field_evidence) leaves its slope within three standard errors: that is
    the tracker's slope prior; without evidence (or with a bad one) the configured prior stays."""
    base = parse_bias_tracking({"enabled": True}, fail).tracker
    fit = {"arw_deg_rt_h": 0.21, "field_evidence": {"slope_dps_per_c": 0.034, "slope_se": 1e-4}}
    tight = base.for_set(fit, arw_given=False)
    assert tight.temp_slope_sigma == pytest.approx(3e-4) and tight.arw_deg_rt_h == 0.21
    assert base.for_set({"field_evidence": {"slope_se": -1.0}}, arw_given=False) is base
    assert base.for_set({"field_evidence": "no"}, arw_given=False) is base
    mixed = base.for_sets([fit, {"arw_deg_rt_h": 0.3}], arw_given=False)
    assert mixed.temp_slope_sigma == base.temp_slope_sigma
    wide = {"field_evidence": {"slope_se": 2e-4}}
    assert base.for_sets([fit, wide], arw_given=False).temp_slope_sigma == pytest.approx(6e-4)
