"""The report reads from top to bottom: the set that was written, then how the loop got there.

A session whose rate model grows once its temperature effect is in (1 segment alone, more with
the effect): the header must name the written size, each held-out figure its scheme, and the
re-selection must be a row of its own whose figure is the written set's.
"""

import json
import re

import pytest
from support.sessions import write_session

from canical.commands.cli import main
from canical.sets import coefficient_file
from canical.sim.scenarios import SCENARIOS


@pytest.fixture(scope="module")
def calibrated(tmp_path_factory):
    folder = tmp_path_factory.mktemp("rep")
    scenario = next(s for s in SCENARIOS if s.name.startswith("temperature bias + scale"))
    session = write_session(folder / "s.csv", scenario.session(0))
    coeffs, rep = folder / "c.yaml", folder / "report"
    assert main(["calibrate", str(session), "-o", str(coeffs), "--report-dir", str(rep)]) == 0
    return coeffs, json.loads((rep / "report.json").read_text()), (rep / "report.md").read_text()


def test_header_describes_the_written_set(calibrated):
    coeffs, report, md = calibrated
    model = coefficient_file.load(coeffs).model
    n_segments = len(model.knots_raw) + 1
    header = next(line for line in md.splitlines() if line.startswith("- coefficient set:"))
    assert f"segments={n_segments} " in header
    assert report["written"]["spec"] in header
    assert report["written"]["effect_terms"] == len(coefficient_file.load(coeffs).terms) > 0
    # This session is the case the header got wrong: the rate model alone is smaller.
    assert report["segments"] != n_segments


def test_every_held_out_figure_names_its_scheme(calibrated):
    _, _, md = calibrated
    rows = [line for line in md.splitlines() if line.startswith("|") and re.search(r"\d\.\d{4}", line)]
    for row in rows:
        if "held-out" in row.split("|")[1]:
            assert "plateau means" in row or "blocks" in row, row
    loop_head = next(line for line in md.splitlines() if line.startswith("| step |"))
    assert "2 s blocks" in loop_head


def test_loop_steps_lead_to_the_written_figure(calibrated):
    _, report, md = calibrated
    loop = report["closed_loop"]
    steps = loop["steps"]
    assert steps[0]["step"] == "rate model alone"
    assert steps[0]["held_out_rms_dps"] == pytest.approx(loop["held_out_rms_before_dps"])
    assert steps[-1]["held_out_rms_dps"] == pytest.approx(loop["held_out_rms_after_dps"])
    assert steps[-1]["spec"] == loop["final_spec"] == report["written"]["spec"]
    names = [s["step"] for s in steps]
    added = names.index("added channel:temp_c")
    assert names[added + 1] == "base size chosen again with the effect in"
    assert steps[added + 1]["spec"] != steps[added]["spec"]
    # The effect's own gain is measured before the size is chosen again, and says so.
    effect = report["effects"][0]
    assert steps[added]["held_out_rms_dps"] == pytest.approx(effect["rms_after_dps"])
    table = [line for line in md.splitlines() if line.startswith("| ") and "segments=" in line]
    figures = [float(re.findall(r"\d+\.\d{4}", line.split("|")[4])[0]) for line in table]
    assert figures == pytest.approx([round(s["held_out_rms_dps"], 4) for s in steps]
                                    + [round(loop["held_out_rms_after_dps"], 4)], abs=1e-4)
