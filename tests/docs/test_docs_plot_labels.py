"""Plot axes carry units: a channel's unit comes from its name's suffix, a transform's from its channel's."""

import pytest

from canical.report.plots import channel_unit, variable_label


@pytest.mark.parametrize(
    ("channel", "unit"),
    [
        ("temp_c", "°C"),
        ("supply_v", "V"),
        ("accel_g", "g"),
        ("rate_dps", "deg/s"),
        ("raw_x", "raw units"),
        ("noise_ch", "units of noise_ch"),
    ],
)
def test_channel_units_from_the_suffix(channel, unit):
    assert channel_unit(channel) == unit


@pytest.mark.parametrize(
    ("name", "label"),
    [
        ("channel:temp_c", "temp_c (°C)"),
        ("d/dt temp_c", "d/dt temp_c (°C/s)"),
        ("lag(temp_c, τ=140 s)", "lag(temp_c, τ=140 s) (°C)"),
        ("temp_c × (|rate| > knee)", "temp_c × (|rate| > knee) (°C)"),
        ("time since power-on", "time since power-on (s)"),
        ("time:linear-drift", "time:linear-drift: time since power-on (s)"),
    ],
)
def test_variable_labels_carry_units(name, label):
    assert variable_label(name) == label
