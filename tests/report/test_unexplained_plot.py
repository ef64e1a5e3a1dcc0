"""``unexplained_residual.png``: its title clear of the panels' titles, each panel's axis its data's.

Issue 33, point 10: the figure's title was drawn over the first row's panel titles
(``tight_layout`` ignores a suptitle), and the temperature panel's axis ran −40…22 for a
temperature of −10…50 (the candidate's feature, the channel less its reference, under a label
in °C).
"""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np
import pytest

from canical.calibration.pipeline import CalibrateOptions, calibrate
from canical.report.plots import LEVEL_PREFIX, unexplained_figure
from canical.sim import environment as env
from canical.sim.gyro import GyroModel
from canical.sim.sessions import paper_rates, sweep_session


@pytest.fixture(scope="module")
def figure():
    """A session whose temperature swings about −17…48 °C, around 20 °C."""
    rates = np.random.default_rng(0).permutation(paper_rates())
    aux = {"temp_c": env.temperature_cycle(mean_c=20.0, amplitude_c=30.0)}
    session = sweep_session(GyroModel(), rates, dwell_s=6.0, seed=0, aux=aux)
    loop = calibrate(session, CalibrateOptions(), sensor_id="S", axis="z").loop
    assert loop is not None
    fig = unexplained_figure(loop)
    fig.canvas.draw()
    yield fig, loop
    plt.close(fig)


def test_the_title_is_above_every_panel_title(figure) -> None:
    fig, _ = figure
    renderer = fig.canvas.get_renderer()
    title = fig.get_suptitle() and fig._suptitle.get_window_extent(renderer)
    panels = [ax for ax in fig.axes if ax.get_title()]
    assert title and len(panels) >= 4
    for ax in panels:
        box = ax.title.get_window_extent(renderer)
        assert box.y1 <= title.y0, (ax.get_title(), box, title)
        assert ax.get_window_extent(renderer).y1 <= title.y0


def test_the_temperature_panel_draws_the_temperature(figure) -> None:
    fig, loop = figure
    temp = loop.blocks.aux["temp_c"]
    lo, hi = float(np.nanmin(temp)), float(np.nanmax(temp))
    assert hi - lo > 50.0
    margin = 0.1 * (hi - lo)
    for name in (f"{LEVEL_PREFIX}temp_c", "lag(temp_c)"):  # both in °C, as their labels say
        ax = next(a for a in fig.axes if a.get_title().startswith(f"{name}  "))
        left, right = ax.get_xlim()
        assert lo - margin <= left and right <= hi + margin, (name, left, right)
        if name.startswith(LEVEL_PREFIX):  # the temperature itself: its whole range
            assert left <= lo and right >= hi, (left, right)
