"""The IMU set file: one CRC over three axes and the coupling; told apart from a single-axis set."""

from dataclasses import replace

import numpy as np
import pytest

from canical.calibration.pipeline import CalibrateOptions, calibrate
from canical.errors import CanicalError
from canical.sets import coefficient_file, imu_set
from canical.sets.corrector import Corrector
from canical.sets.imu_corrector import ImuCorrector
from canical.sets.imu_set import ImuSet, as_matrix
from canical.sim.sessions import paper_session

COUPLING = [[1.0, 0.012, -0.008], [0.015, 1.0, 0.004], [-0.02, 0.006, 1.0]]


@pytest.fixture(scope="module")
def single():
    return calibrate(paper_session(seed=3, dwell_s=2.0), CalibrateOptions(extend=False), sensor_id="IMU-7",
                     axis="z").coefficients


@pytest.fixture(scope="module")
def imu(single):
    axes = tuple(replace(single, axis=a) for a in "xyz")
    return ImuSet("IMU-7", axes, as_matrix(COUPLING), as_matrix(np.full((3, 3), 1e-5)),  # type: ignore[arg-type]
                  {"coupling_plateaus": 120}, "2026-01-01T00:00:00Z")


def test_round_trip_and_one_crc(imu, tmp_path):
    path = tmp_path / "imu.yaml"
    imu_set.save(path, imu)
    text = path.read_text()
    assert text.count("crc32") == 1 and text.splitlines()[1] == "kind: imu-set"
    back = imu_set.load(path)
    assert back == imu
    assert imu_set.imu_set_crc(back) == imu_set.imu_set_crc(imu)
    assert imu_set.is_imu_set_file(path)


def test_a_damaged_file_is_refused(imu, tmp_path):
    path = tmp_path / "imu.yaml"
    imu_set.save(path, imu)
    path.write_text(path.read_text().replace("0.012", "0.013"))
    with pytest.raises(CanicalError, match="CRC mismatch"):
        imu_set.load(path)


def test_the_two_kinds_are_told_apart(imu, single, tmp_path):
    one, three = tmp_path / "one.yaml", tmp_path / "three.yaml"
    coefficient_file.save(one, single)
    imu_set.save(three, imu)
    assert coefficient_file.load(one) == single  # a single-axis set loads exactly as before
    assert not imu_set.is_imu_set_file(one)
    with pytest.raises(CanicalError, match=r"an IMU set .*not a single-axis coefficient set"):
        coefficient_file.load(three)
    with pytest.raises(CanicalError, match="a single-axis coefficient set, not an IMU set"):
        imu_set.load(one)


@pytest.mark.parametrize(("matrix", "message"), [
    ([[1, 0.12, 0], [0, 1, 0], [0, 0, 1]], r"coupling term xy is \+12.0 %, above 10 %"),
    ([[1, 0, 0], [0, 1, 0], [0, 0, 0]], r"coupling term zz is 0, outside 0.5..2"),
    ([[1e308, 0, 0], [0, 1e308, 0], [0, 0, 1e308]], r"coupling term xx is 1e\+308, outside 0.5..2"),
    ([[1e-300, 0, 0], [0, 1e-300, 0], [0, 0, 1e-300]], r"coupling term xx is 1e-300, outside 0.5..2"),
    ([[-1, 0, 0], [0, -1, 0], [0, 0, -1]], r"coupling term xx is -1, outside 0.5..2"),
    ([[1, 0, 0], [0, 1, 0], [0, 0, 2e-3]], r"coupling term zz is 0.002, outside 0.5..2: .*near identity"),
    ([[1, 0, 0], [0, 1, 0], [1, 1, 1, 1]], "3 rows of 3 finite numbers"),
])
def test_an_implausible_coupling_is_refused(imu, matrix, message):
    content = imu.to_dict()
    content["coupling"]["matrix"] = matrix
    content["crc32"] = f"0x{coefficient_file.content_crc(content):08x}"
    with pytest.raises(CanicalError, match=message):
        imu_set.from_content(content, "imu.yaml")


def test_negative_standard_errors_are_refused(imu):
    content = imu.to_dict()
    content["coupling"]["standard_errors"][1][2] = -1e-4
    content["crc32"] = f"0x{coefficient_file.content_crc(content):08x}"
    with pytest.raises(CanicalError, match="standard_errors must not be negative"):
        imu_set.from_content(content, "imu.yaml")


def test_the_finite_outputs_proof_covers_the_coupling():
    """Per-axis bounds each within the limit, but a row of the product beyond it: refused."""
    from canical.sets.finite_outputs import RATE_LIMIT_DPS, check_coupled_outputs

    near = (0.95 * RATE_LIMIT_DPS,) * 3
    assert check_coupled_outputs(np.eye(3), near) is None
    unbounded = check_coupled_outputs(np.asarray(COUPLING) * 1.05, near)
    assert unbounded is not None and "row 1" in unbounded.message()
    assert check_coupled_outputs(np.eye(3), (1.0, 1.0, float("inf"))) is not None


def test_the_corrector_couples_the_per_axis_rates(imu, single):
    raw = np.column_stack([np.linspace(-5000, 5000, 7), np.linspace(3000, -3000, 7), np.full(7, 1200.0)])
    rates, flags = ImuCorrector(imu).correct(raw)
    per_axis = np.column_stack([Corrector(single).correct(raw[:, i])[0] for i in range(3)])
    np.testing.assert_allclose(rates, per_axis @ np.asarray(COUPLING).T, rtol=1e-12)
    assert flags.shape == (7, 3) and not flags.any()
