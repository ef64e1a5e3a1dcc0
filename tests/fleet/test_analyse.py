"""``canical fleet analyse``: on a small simulated fleet the planted aging and failing sensors are
found and the good ones not flagged, the field slopes lie within their standard errors of the
truth; a real Dask cluster (a scheduler and two worker processes on the loopback) gives the same
``sensors.csv`` as the embedded engine, byte for byte."""

from __future__ import annotations

import csv
from pathlib import Path

import pytest

from canical.commands.cli import main

VEHICLES, DAYS, SEED = 40, 20, 1  # seed 1: three aging and two failing sensors among 40


@pytest.fixture(scope="module")
def fleet(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The simulated fleet's folder (with truth.csv) and its ingested dataset."""
    root = tmp_path_factory.mktemp("fleet")
    assert main(["simulate", "fleet", "--vehicles", str(VEHICLES), "--days", str(DAYS), "--seed", str(SEED),
                 "-o", str(root / "logs")]) == 0
    assert main(["fleet", "ingest", str(root / "logs"), "-o", str(root / "dataset")]) == 0
    return root / "logs", root / "dataset"


def rows(path: Path) -> dict[str, dict[str, str]]:
    return {r["sensor_id"]: r for r in csv.DictReader(path.open())}


def test_planted_sensors_are_found_and_good_ones_are_not_flagged(fleet: tuple[Path, Path], tmp_path: Path,
                                                                capsys: pytest.CaptureFixture[str]) -> None:
    logs, data = fleet
    assert main(["fleet", "analyse", str(data), "--report-dir", str(tmp_path / "r")]) == 0
    assert "2 out of spec, 3 drifting" in capsys.readouterr().out
    truth, got = rows(logs / "truth.csv"), rows(tmp_path / "r" / "sensors.csv")
    assert sorted(got) == sorted(truth)
    assert {s: got[s]["verdict"] for s in got} == {s: truth[s]["verdict"] for s in truth}
    z = [abs(float(got[s]["slope_dps_per_c"]) - float(truth[s]["slope_dps_per_c"]))
         / float(got[s]["slope_se"]) for s in truth]
    # 95 % within 2 SE is judged on 1,000 vehicles (docs/fleet.md); 40 leave room for chance (35 here)
    assert sum(x <= 2 for x in z) >= 0.8 * len(z) and max(z) < 3.5
    # a spread from 35-45 power-ons is known to about 12 % (1σ): the worst of 40 is 35 % off here
    error = [abs(float(got[s]["spread_dps"]) / float(truth[s]["turn_on_spread_dps"]) - 1) for s in truth]
    assert max(error) < 0.45 and sorted(error)[len(error) // 2] < 0.12
    report = (tmp_path / "r" / "report.md").read_text()
    assert "## Listed for maintenance" in report and all(
        s in report for s in truth if truth[s]["verdict"] != "in spec")
    plots = ("spread.png", "slope.png", "drift.png")
    assert all((tmp_path / "r" / name).stat().st_size > 1000 for name in plots)


def test_a_cluster_of_two_worker_processes_gives_the_same_sensors_csv(fleet: tuple[Path, Path],
                                                                      tmp_path: Path) -> None:
    distributed = pytest.importorskip("distributed")
    _, data = fleet
    assert main(["fleet", "analyse", str(data), "--report-dir", str(tmp_path / "embedded")]) == 0
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None) as cluster:
        assert cluster.scheduler_address.startswith("tcp://127.0.0.1:")
        assert main(["fleet", "analyse", str(data), "--report-dir", str(tmp_path / "cluster"),
                     "--scheduler", cluster.scheduler_address]) == 0
    embedded = (tmp_path / "embedded" / "sensors.csv").read_bytes()
    assert (tmp_path / "cluster" / "sensors.csv").read_bytes() == embedded


@pytest.mark.parametrize(("argv", "message"), [
    (["--scheduler", "localhost:8786"], "give the scheduler's address, tcp://HOST:PORT"),
    (["--scheduler", "tcp://127.0.0.1:9"], "cannot connect"),
])
def test_a_bad_scheduler_is_one_line(fleet: tuple[Path, Path], tmp_path: Path,
                                     capsys: pytest.CaptureFixture[str],
                                     argv: list[str],
                                     message: str) -> None:
    assert main(["fleet", "analyse", str(fleet[1]), "--report-dir", str(tmp_path / "r"), *argv]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and not (tmp_path / "r").exists()


def test_a_folder_that_is_no_dataset_is_one_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["fleet", "analyse", str(tmp_path), "--report-dir", str(tmp_path / "r")]) == 2
    assert "not a dataset fleet ingest wrote" in capsys.readouterr().err


def test_a_sensor_without_temperature_gets_a_spread_and_no_slope(tmp_path: Path) -> None:
    """A vehicle whose daemon had no temperature input: the spread and drift are judged, the slope is
    not (empty in sensors.csv), never a crash."""
    import dataclasses

    from canical.fieldlog import segments
    from canical.sim.fleet import simulate_vehicle

    records = [dataclasses.replace(r, temp_c=None) for r in simulate_vehicle(5, 10, seed=2)[1]]
    (tmp_path / "logs").mkdir()
    for number, data in enumerate(segments.pack(records)):
        (tmp_path / "logs" / segments.segment_name(number)).write_bytes(data)
    assert main(["fleet", "ingest", str(tmp_path / "logs"), "-o", str(tmp_path / "ds")]) == 0
    assert main(["fleet", "analyse", str(tmp_path / "ds"), "--report-dir", str(tmp_path / "r")]) == 0
    (row,) = rows(tmp_path / "r" / "sensors.csv").values()
    assert row["slope_dps_per_c"] == "" and float(row["spread_dps"]) > 0 and int(row["records"]) > 10


def test_a_sensor_table_names_the_lots(fleet: tuple[Path, Path], tmp_path: Path,
                                       capsys: pytest.CaptureFixture[str]) -> None:
    logs, data = fleet
    table = tmp_path / "lots.csv"
    sensors = rows(logs / "truth.csv")
    table.write_text("sensor_id,lot\n" + "".join(f"{s},L{i % 2}\n" for i, s in enumerate(sensors)))
    analyse = ["fleet", "analyse", str(data), "--lots", str(table), "--report-dir"]
    assert main([*analyse, str(tmp_path / "r")]) == 0
    assert {r["lot"] for r in rows(tmp_path / "r" / "sensors.csv").values()} == {"L0", "L1"}
    assert "| L0 | 20 |" in (tmp_path / "r" / "report.md").read_text()
    table.write_text("sensor,batch\nx,y\n")
    assert main([*analyse, str(tmp_path / "s")]) == 2
    assert "a CSV with sensor_id and lot columns" in capsys.readouterr().err


def test_a_worker_killed_in_the_middle_changes_nothing(fleet: tuple[Path, Path], tmp_path: Path,
                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    """One of two worker processes is killed (SIGKILL) once some of the tasks are done: the cluster
    runs the lost ones again elsewhere and sensors.csv is the undisturbed run's, byte for byte."""
    distributed = pytest.importorskip("distributed")
    from support.worker_kill import worker_killed_after

    from canical.fleet import engine

    monkeypatch.setattr(engine, "BATCH", 1)  # a task per vehicle: 40 tasks, the kill lands among them
    _, data = fleet
    assert main(["fleet", "analyse", str(data), "--report-dir", str(tmp_path / "embedded")]) == 0
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None) as cluster, \
            worker_killed_after(cluster.scheduler_address, 3) as killed:
        assert main(["fleet", "analyse", str(data), "--report-dir", str(tmp_path / "cluster"),
                     "--scheduler", cluster.scheduler_address]) == 0
    assert killed and killed[0] < VEHICLES  # killed while tasks were left
    embedded = (tmp_path / "embedded" / "sensors.csv").read_bytes()
    assert (tmp_path / "cluster" / "sensors.csv").read_bytes() == embedded


def test_per_set_id_distributions_show_shared_generations(fleet: tuple[Path, Path], tmp_path: Path) -> None:
    """sensors.csv names each sensor's set id; report.md gives per shared set id (a calibration
    generation several sensors carry) the verdicts and the spread and slope distributions, and
    says so when every set id is one sensor's (the simulated fleet: a set per sensor)."""
    import dataclasses

    from canical.fleet.analysis import IN_SPEC, SensorVerdict
    from canical.fleet.report import per_set_id

    _, data = fleet
    assert main(["fleet", "analyse", str(data), "--report-dir", str(tmp_path / "r")]) == 0
    got = rows(tmp_path / "r" / "sensors.csv")
    assert len({r["set_id"] for r in got.values()}) == VEHICLES
    report = (tmp_path / "r" / "report.md").read_text()
    assert f"Every set id here is one sensor's ({VEHICLES} set ids" in report
    assert "| lot | sensors | in spec | drifting | out of spec | spread deg/s: median (10–90 %)" in report
    base = SensorVerdict("A-1", "z", IN_SPEC, 0.001, 1e-4, 0.1, 0.0, 1e-3, 50, 10, 1, 20.0, 0xAB)
    shared = [dataclasses.replace(base, sensor_id=f"A-{i}", spread_dps=0.1 * i) for i in range(1, 6)]
    lines = per_set_id([*shared, dataclasses.replace(base, sensor_id="B-1", set_id=7)])
    assert "| 0x000000ab | 5 | 5 | 0 | 0 | 0.300 (0.140 to 0.460) | +0.0010 (+0.0010 to +0.0010) |" in lines
    assert lines[-1] == "1 further set ids are one sensor's each."
