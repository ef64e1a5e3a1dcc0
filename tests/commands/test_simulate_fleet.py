"""``canical simulate fleet``: field-log segments per vehicle that every reader reads, the truth
beside them, vehicle k the same whatever the fleet's size; misuse is one line."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from canical.commands.cli import main
from canical.fieldlog import segments
from canical.fieldlog.record import ADOPTED, POWER_ON, REFUSED
from canical.sim.fleet import DRIFTING, OUT_OF_SPEC, simulate_vehicle


def test_a_fleet_is_a_folder_of_segments_per_vehicle_and_its_truth(
        tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    out = tmp_path / "fleet"
    assert main(["simulate", "fleet", "--vehicles", "6", "--days", "4", "-o", str(out), "--seed", "3"]) == 0
    assert "fleet of 6 vehicles over 4 days" in capsys.readouterr().out
    truth = list(csv.DictReader((out / "truth.csv").open()))
    assert [t["vehicle_id"] for t in truth] == [f"veh-{k:05d}" for k in range(6)]
    for row in truth:
        skipped: list[str] = []
        paths = segments.segment_paths(out / row["vehicle_id"])
        got = [r for s in segments.read_segments(paths, skipped.append) for r in s.records]
        assert skipped == [] and {r.sensor_id for r in got} == {row["sensor_id"]}
        assert got == simulate_vehicle(int(row["vehicle_id"][4:]), 4, 3)[1]
        assert {r.decision for r in got} <= {ADOPTED, REFUSED, POWER_ON} and got[0].decision == POWER_ON


def test_vehicle_k_is_the_same_whatever_the_fleets_size_and_plants_are_rare() -> None:
    assert simulate_vehicle(7, 3, 0) == simulate_vehicle(7, 3, 0)
    verdicts = [simulate_vehicle(k, 1, 0)[0].verdict for k in range(400)]
    assert 0 < verdicts.count(DRIFTING) < 30 and 0 < verdicts.count(OUT_OF_SPEC) < 20


@pytest.mark.parametrize(("argv", "message"), [
    (["--vehicles", "3"], "give --vehicles N and --days D"),
    (["--vehicles", "0", "--days", "1"], "--vehicles is 1..100000"),
])
def test_misuse_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str], argv: list[str],
                            message: str) -> None:
    assert main(["simulate", "fleet", "-o", str(tmp_path / "f"), *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and err.count("\n") == 1


def test_a_folder_with_something_in_it_is_refused(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "keep.txt").write_text("mine")
    assert main(["simulate", "fleet", "--vehicles", "1", "--days", "1", "-o", str(tmp_path)]) == 2
    assert "not an empty folder" in capsys.readouterr().err
    assert main(["simulate", "drive", "--days", "1", "-o", str(tmp_path / "d.csv")]) == 2
    assert "--vehicles, --days and --drives are for simulate fleet" in capsys.readouterr().err


def test_drives_come_with_their_baseline_sets(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """--drives K: per vehicle K raw drives naming their sensor, and the sensor's baseline set
    (--drive-set under its id); the raw values give the drive's rate back through that set."""
    from canical.fleet.replay import blocks
    from canical.sets import coefficient_file
    from canical.sets.corrector import Corrector

    template = Path(__file__).parents[1] / "data" / "sets" / "daemon-z.yaml"
    assert main(["simulate", "fleet", "--vehicles", "2", "--days", "1", "--drives", "2", "--drive-set",
                 str(template), "-o", str(tmp_path / "f")]) == 0
    drives = sorted((tmp_path / "f" / "drives").rglob("*.csv"))
    assert [p.relative_to(tmp_path / "f" / "drives").as_posix() for p in drives] == [
        "veh-00000/drive-000.csv", "veh-00000/drive-001.csv", "veh-00001/drive-000.csv",
        "veh-00001/drive-001.csv"]
    sensor = drives[0].read_text().splitlines()[0].removeprefix("# sensor: ")
    cset = coefficient_file.load(tmp_path / "f" / "sets" / f"{sensor}.yaml")
    cols = next(blocks(drives[0]))
    rate, _ = Corrector(cset).correct(cols["raw"])
    stopped = cols["speed_mps"] == 0
    assert abs(float((rate - cols["true_rate_dps"])[stopped].mean())) < 1.5  # the sensor's bias, no more
    assert main(["simulate", "fleet", "--vehicles", "1", "--days", "1", "--drives", "1",
                 "-o", str(tmp_path / "g")]) == 2
    assert "--drives K (1..100) and --drive-set SET go together" in capsys.readouterr().err


def test_a_drives_temperature_slope_is_stated_at_the_field_logs_reference() -> None:
    """The drive's sensor is the field log's: its bias is the turn-on bias plus the slope times
    (temperature - 25 °C), the reference the field log and a proposed set's term use (a cold
    vehicle's drive starting at -5 °C starts 30 °C from it)."""
    from canical.sim.fleet import REFERENCE_C
    from canical.sim.fleet_drives import drive_for

    truth, _ = simulate_vehicle(0, 1, 15)
    drive = drive_for(truth, 0, 0, 15)
    first = drive.cycle == 0
    no_temp = drive.bias_dps[first] - truth.slope_dps_per_c * (drive.temp_c[first] - REFERENCE_C)
    assert abs(float(no_temp.mean()) - truth.turn_on_mean_dps) < 0.01
