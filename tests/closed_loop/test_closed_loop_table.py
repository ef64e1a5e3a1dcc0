"""The closed loop's scenario results still hold when the sessions are recorded the way real
tables record them: ramps at 10 deg/s² between plateaus and the table's measured rate as the
reference (0.02 deg/s rms jitter, 0.001 deg/s encoder steps)."""

import pytest

from canical.calibration.evaluation import score_scenario
from canical.sim.scenarios import SCENARIOS
from canical.sim.table_recording import TableBehaviour

RAMPED_JITTERED = TableBehaviour(accel_dps2=10.0, reference="measured", jitter_dps=0.02,
                                 encoder_lsb_dps=0.001)


@pytest.mark.parametrize("scenario", SCENARIOS, ids=[s.name for s in SCENARIOS])
def test_scenario_on_a_ramped_jittered_table(scenario):
    r = score_scenario(scenario, seed=3, dwell_s=8.0, table=RAMPED_JITTERED)
    assert set(r.found) == set(scenario.expect)
    if scenario.confounded:
        assert r.confounded, "confounded candidates must be reported"
        assert set(scenario.confounded) <= {n for g in r.confounded for n in g}
        assert r.rms_after < r.rms_before / 3 and r.rms_after <= 2.0 * r.rms_oracle  # one adopted
    else:
        assert not r.confounded
    if scenario.expect:
        assert r.rms_after < r.rms_before / 3
        assert r.rms_after <= 1.5 * r.rms_oracle
    if not scenario.effects:
        assert r.rms_after == pytest.approx(r.rms_before)
