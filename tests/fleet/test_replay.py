"""``fleet replay``: recorded raw drives through the baseline and the proposed sets and the bias
tracker. On a small simulated fleet (seed 15: vehicle 0's sensor leaves a slope of 0.034 deg/s/°C
over its set) the proposed set cuts the zero-rate error at standstills, and a sensor without a
proposal replays the same figures before and after; a real Dask cluster (two worker processes on
the loopback), with or without one of them killed mid-run, gives the embedded engine's
``replay.csv`` byte for byte."""

from __future__ import annotations

import csv
import math
from pathlib import Path

import pytest

from canical.commands.cli import main

VEHICLES, DAYS, SEED = 8, 20, 15
WRONG = "D26-00000"  # planted: a slope error of 0.034 deg/s/°C
SET = Path(__file__).parents[1] / "data" / "sets" / "daemon-z.yaml"


@pytest.fixture(scope="module")
def replayed(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """The fleet's folder: field logs, drives, baseline sets, proposed sets (new/) and the embedded
    replay's replay.csv."""
    root = tmp_path_factory.mktemp("replay")
    assert main(["simulate", "fleet", "--vehicles", str(VEHICLES), "--days", str(DAYS), "--seed", str(SEED),
                 "--drives", "1", "--drive-set", str(SET), "-o", str(root)]) == 0
    assert main(["fleet", "ingest", str(root), "-o", str(root / "dataset")]) == 0
    assert main(["fleet", "analyse", str(root / "dataset"), "--report-dir", str(root / "report"),
                 "--propose-sets", str(root / "sets"), "-o", str(root / "new")]) == 0
    assert main(["fleet", "replay", str(root / "drives"), "--sets", str(root / "new"),
                 "--baseline", str(root / "sets"), "-o", str(root / "replay.csv")]) == 0
    return root


def rows(path: Path) -> dict[str, dict[str, str]]:
    return {r["sensor_id"]: r for r in csv.DictReader(path.open())}


def test_the_proposed_set_cuts_the_zero_rate_error_and_the_others_stay(replayed: Path) -> None:
    got, proposals = rows(replayed / "replay.csv"), rows(replayed / "new" / "proposals.csv")
    assert len(got) == VEHICLES and all(int(r["standstills"]) >= 5 for r in got.values())
    wrong = got[WRONG]
    # carried into the standstills: 0.021 -> 0.0022 deg/s (9.5x) here (docs/fleet.md)
    assert float(wrong["carried_before_dps"]) >= 5 * float(wrong["carried_after_dps"])
    # with the tracked bias (the tracker re-learning within each stop): 0.0071 -> 0.0021, less
    assert 2 * float(wrong["zero_rate_after_dps"]) < float(wrong["zero_rate_before_dps"])
    unchanged = [s for s, p in proposals.items() if p["outcome"] == "unchanged"]
    assert unchanged
    for sensor in unchanged:  # the same set twice: the same figures, to the last digit
        assert got[sensor]["carried_before_dps"] == got[sensor]["carried_after_dps"]
        assert got[sensor]["zero_rate_before_dps"] == got[sensor]["zero_rate_after_dps"]
        assert got[sensor]["heading_before_deg"] == got[sensor]["heading_after_deg"]
        assert got[sensor]["carried_less_noise_before_dps"] == got[sensor]["carried_less_noise_after_dps"]


def test_the_carried_error_less_its_noise_is_below_the_carried_error(replayed: Path) -> None:
    """Each vehicle's standstills' own noise (from their one-second means) is what the carried
    figure holds beyond the error: in quadrature, carried² = less-noise² + noise² (floored at 0)."""
    for r in rows(replayed / "replay.csv").values():
        for when in ("before", "after"):
            carried, noise = float(r[f"carried_{when}_dps"]), float(r[f"carried_noise_{when}_dps"])
            less = float(r[f"carried_less_noise_{when}_dps"])
            assert 0.0005 < noise < 0.003  # a 15 s stop's mean: 0.05 deg/s white, the idle tone averaged out
            assert less == pytest.approx(math.sqrt(max(carried**2 - noise**2, 0.0)), rel=1e-4, abs=1e-9)
            assert float(r[f"carried_less_noise_{when}_sd_dps"]) > 0


def test_a_drive_folder_without_sets_is_one_line(replayed: Path, tmp_path: Path,
                                                 capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "empty").mkdir()
    assert main(["fleet", "replay", str(replayed / "drives"), "--sets", str(replayed / "new"),
                 "--baseline", str(tmp_path / "empty")]) == 2
    err = capsys.readouterr().err
    assert "no single-axis set files" in err and "Traceback" not in err


def test_a_cluster_with_a_worker_killed_gives_the_embedded_result(replayed: Path, tmp_path: Path) -> None:
    """Two worker processes; one run undisturbed, one with a worker killed (SIGKILL) once two
    drives are done: both replay.csv files are the embedded engine's, byte for byte."""
    distributed = pytest.importorskip("distributed")
    from support.worker_kill import worker_killed_after

    argv = ["fleet", "replay", str(replayed / "drives"), "--sets", str(replayed / "new"),
            "--baseline", str(replayed / "sets")]
    with distributed.LocalCluster(n_workers=2, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None) as cluster:
        address = cluster.scheduler_address
        assert main([*argv, "--scheduler", address, "-o", str(tmp_path / "calm.csv")]) == 0
        with worker_killed_after(address, 2) as killed:
            assert main([*argv, "--scheduler", address, "-o", str(tmp_path / "killed.csv")]) == 0
    assert killed and killed[0] < VEHICLES  # killed while drives were left
    embedded = (replayed / "replay.csv").read_bytes()
    assert (tmp_path / "calm.csv").read_bytes() == embedded
    assert (tmp_path / "killed.csv").read_bytes() == embedded


def test_a_parquet_drive_replays_as_its_csv(replayed: Path, tmp_path: Path) -> None:
    """The same drive as Parquet (columns as the CSV's, the sensor in its metadata) gives the
    same figures, though read in other blocks."""
    import pyarrow as pa
    import pyarrow.parquet as pq

    from canical.fleet.replay import blocks

    drive = replayed / "drives" / "veh-00000" / "drive-000.csv"
    cols: dict[str, list[float]] = {}
    for block in blocks(drive):
        for name, values in block.items():
            cols.setdefault(name, []).extend(values.tolist())
    (tmp_path / "pq" / "veh-00000").mkdir(parents=True)
    (tmp_path / "csv" / "veh-00000").mkdir(parents=True)
    table = pa.table(cols).replace_schema_metadata({"sensor": WRONG})
    pq.write_table(table, tmp_path / "pq" / "veh-00000" / "drive-000.parquet")
    (tmp_path / "csv" / "veh-00000" / "drive-000.csv").write_bytes(drive.read_bytes())
    for kind in ("pq", "csv"):
        assert main(["fleet", "replay", str(tmp_path / kind), "--sets", str(replayed / "new"),
                     "--baseline", str(replayed / "sets"), "-o", str(tmp_path / f"{kind}.csv")]) == 0
    assert rows(tmp_path / "pq.csv") == rows(tmp_path / "csv.csv")
    assert rows(tmp_path / "pq.csv")[WRONG] == rows(replayed / "replay.csv")[WRONG]


#: Scales that are powers of two: a decoded value is the CSV's exactly (a last-bit difference
#: can flip one of the tracker's decisions, and the figures with it).
DRIVE_DBC = """VERSION ""
NS_ :
BS_:
BU_: IMU CAR
BO_ 400 IMU_RAW: 8 IMU
 SG_ GyroRawZ : 0|32@1- (0.0009765625,0) [-2000000|2000000] "counts" CAR
 SG_ Temp : 32|16@1- (0.0078125,0) [-250|250] "degC" CAR
BO_ 401 DRIVE: 8 CAR
 SG_ Speed : 0|32@1- (0.0009765625,0) [-1000|1000] "m/s" IMU
 SG_ Uptime : 32|32@1+ (0.0078125,0) [0|30000000] "s" IMU
BO_ 402 TRUTH: 8 CAR
 SG_ TrueRate : 0|32@1- (0.0000152587890625,0) [-30000|30000] "deg/s" IMU
"""
STEPS = {"time_s": 2**-7, "raw": 2**-10, "temp_c": 2**-7, "speed_mps": 2**-10, "true_rate_dps": 2**-16}
LOG_INPUTS = ["--input", "temp_c=IMU_RAW.Temp", "--input", "speed_mps=DRIVE.Speed",
              "--input", "time_s=DRIVE.Uptime", "--input", "true_rate_dps=TRUTH.TrueRate"]


def write_drive_log(path: Path, cols: dict[str, list[float]], dbc: Path) -> None:
    """The drive's rows as frames: per row DRIVE and TRUTH (held), then the raw frame."""
    import can
    import cantools

    db = cantools.database.load_file(dbc)
    writer = can.Logger(str(path))
    try:
        for i, t in enumerate(cols["time_s"]):
            stamp = 1_700_000_000.0 + t
            for name, values in (("DRIVE", {"Speed": cols["speed_mps"][i], "Uptime": t}),
                                 ("TRUTH", {"TrueRate": cols["true_rate_dps"][i]}),
                                 ("IMU_RAW", {"GyroRawZ": cols["raw"][i], "Temp": cols["temp_c"][i]})):
                msg = db.get_message_by_name(name)
                writer.on_message_received(can.Message(timestamp=stamp, arbitration_id=msg.frame_id,
                                                       data=msg.encode(values), is_extended_id=False))
    finally:
        writer.stop()


@pytest.mark.parametrize("suffix", [".log", ".asc"])
def test_a_can_log_drive_replays_as_its_csv(replayed: Path, tmp_path: Path, suffix: str) -> None:
    """The same drive (its first power-on) as a CSV and as a CAN log (candump or Vector ASC,
    written by python-can) decoded with a DBC and --input: the same figures; on a worker process
    too."""
    drive = replayed / "drives" / "veh-00000" / "drive-000.csv"
    head, *lines = drive.read_text().splitlines()[2:40_003]
    names = head.split(",")
    cols = {n: [round(float(line.split(",")[i]) / STEPS[n]) * STEPS[n] for line in lines]
            for i, n in enumerate(names)}
    assert cols["time_s"] == sorted(cols["time_s"])  # one power-on
    (tmp_path / "dbc.dbc").write_text(DRIVE_DBC)
    for kind in ("csv", "log"):
        (tmp_path / kind / "veh-00000").mkdir(parents=True)
    table = "\n".join(",".join(repr(cols[n][i]) for n in names) for i in range(len(lines)))
    (tmp_path / "csv" / "veh-00000" / "drive-000.csv").write_text(f"# sensor: {WRONG}\n{head}\n{table}\n")
    write_drive_log(tmp_path / "log" / "veh-00000" / f"drive-000{suffix}", cols, tmp_path / "dbc.dbc")
    argv = ["fleet", "replay", "--sets", str(replayed / "new"), "--baseline", str(replayed / "sets")]
    assert main([*argv, str(tmp_path / "csv"), "-o", str(tmp_path / "csv.csv")]) == 0
    layout = ["--dbc", str(tmp_path / "dbc.dbc"), "--input", "raw=IMU_RAW.GyroRawZ", *LOG_INPUTS,
              "--sensor", WRONG]
    assert main([*argv, str(tmp_path / "log"), "-o", str(tmp_path / "log.csv"), *layout]) == 0
    want = rows(tmp_path / "csv.csv")[WRONG]
    assert int(want["standstills"]) >= 3
    assert rows(tmp_path / "log.csv")[WRONG] == want  # the same values, decoded exactly: the same figures
    if suffix == ".log":  # the log's layout travels to a worker process with its task
        distributed = pytest.importorskip("distributed")
        with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                                      dashboard_address=None) as cluster:
            assert main([*argv, str(tmp_path / "log"), "-o", str(tmp_path / "worker.csv"), *layout,
                         "--scheduler", cluster.scheduler_address]) == 0
        assert (tmp_path / "worker.csv").read_bytes() == (tmp_path / "log.csv").read_bytes()


@pytest.mark.parametrize(("extra", "message"), [
    ([], "reading a CAN log needs --dbc or --config"),
    (["--input", "raw=IMU_RAW.GyroRawZ"], "reading a CAN log needs --dbc or --config"),
    (["--dbc", "DBC", "--input", "raw=IMU_RAW.GyroRawZ"],
     "names no sensor (a CAN log's: --sensor or --config)"),
    (["--dbc", "DBC", "--input", "raw=IMU_RAW.GyroRawZ", "--sensor", WRONG],
     "a CAN log's drive needs channel 'speed_mps': map it with --input speed_mps=MESSAGE.Signal or --config"),
])
def test_a_can_log_without_its_layout_is_one_line(replayed: Path, tmp_path: Path, extra: list[str],
                                                  message: str, capsys: pytest.CaptureFixture[str]) -> None:
    (tmp_path / "dbc.dbc").write_text(DRIVE_DBC)
    (tmp_path / "veh-00000").mkdir()
    one_row = {"time_s": [0.0], "raw": [1.0], "temp_c": [20.0], "speed_mps": [0.0], "true_rate_dps": [0.0]}
    write_drive_log(tmp_path / "veh-00000" / "drive.log", one_row, tmp_path / "dbc.dbc")
    extra = [str(tmp_path / "dbc.dbc") if a == "DBC" else a for a in extra]
    assert main(["fleet", "replay", str(tmp_path), "--sets", str(replayed / "new"), "--baseline",
                 str(replayed / "sets"), *extra]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err and len(err.strip().splitlines()) == 1
