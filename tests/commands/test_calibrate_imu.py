"""`canical calibrate x.csv y.csv z.csv -o imu.yaml` and `canical apply imu.yaml drive.csv` as a user
runs them: one IMU set and its report, three corrected rates; bad inputs one line, exit 2, nothing written."""

import json
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
from support.triad import write_triad_sessions

from canical.commands.cli import main
from canical.sessions.csv_file import read_table
from canical.sets import imu_set

DBC = Path(__file__).resolve().parents[2] / "dbc" / "canical.dbc"


@pytest.fixture(scope="module")
def sessions(tmp_path_factory):
    return write_triad_sessions(tmp_path_factory.mktemp("triad"), seed=2)


@pytest.fixture(scope="module")
def calibrated(sessions, tmp_path_factory):
    out = tmp_path_factory.mktemp("out")
    imu, rep = out / "imu.yaml", out / "rep"
    assert main(["calibrate", *map(str, sessions), "-o", str(imu), "--report-dir", str(rep)]) == 0
    return imu, rep


def test_calibrate_writes_an_imu_set_and_its_report(calibrated, capsys):
    imu, rep = calibrated
    loaded = imu_set.load(imu)
    assert [c.axis for c in loaded.axes] == ["x", "y", "z"]
    assert sorted(p.name for p in rep.iterdir()) == ["coupling.png", "report.json", "report.md"]
    report = json.loads((rep / "report.json").read_text())
    assert len(report["coupling"]["off_diagonal"]) == 6
    assert all({"percent", "mrad", "standard_error"} <= set(t) for t in report["coupling"]["off_diagonal"])
    multi = report["held_out"][-1]
    assert multi["axis"] == "multi"
    assert max(multi["after_rms_dps"].values()) < 0.02 < min(multi["before_rms_dps"].values())
    md = (rep / "report.md").read_text()
    assert "## Coupling" in md and "mrad" in md and "![coupling.png](coupling.png)" in md


def test_apply_appends_three_rates(calibrated, sessions, tmp_path):
    imu, _ = calibrated
    drive, out = sessions[-1], tmp_path / "out.csv"
    assert main(["apply", str(imu), str(drive), "-o", str(out)]) == 0
    text_in, text_out = drive.read_text().splitlines(), out.read_text().splitlines()
    assert len(text_in) == len(text_out)
    new = ",rate_x_dps,rate_y_dps,rate_z_dps,out_of_span_x,out_of_span_y,out_of_span_z"
    assert text_out[2] == text_in[2] + new
    assert all(o.startswith(i + ",") for i, o in zip(text_in[3:50], text_out[3:50], strict=True))
    t = read_table(out).columns
    err = np.column_stack([t[f"rate_{a}_dps"] - t[f"ref_{a}_dps"] for a in "xyz"])
    assert np.median(np.abs(err)) < 0.2  # single samples: noise 0.08 deg/s, and the ramps


def run(*argv):
    return subprocess.run([sys.executable, "-m", "canical", *map(str, argv)], capture_output=True, text=True)


def one_line_exit_2(proc, message):
    assert proc.returncode == 2, proc.stderr
    assert message in proc.stderr
    assert proc.stderr.count("\n") == 1 and "Traceback" not in proc.stderr


def edited(path, tmp_path, name, change):
    lines = path.read_text().splitlines()
    new = tmp_path / name
    new.write_text("\n".join(change(lines)) + "\n")
    return new


def drop_column(lines, column):
    k = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    index = lines[k].split(",").index(column)
    return lines[:k] + [",".join(c for j, c in enumerate(line.split(",")) if j != index)
                        for line in lines[k:]]


def askew(lines):
    """raw_y takes 20 % of raw_x: an axis mounted askew, not a sensor's coupling."""
    k = next(i for i, line in enumerate(lines) if not line.startswith("#"))
    head = lines[k].split(",")
    x, y = head.index("raw_x"), head.index("raw_y")
    rows = [line.split(",") for line in lines[k + 1:]]
    for r in rows:
        r[y] = repr(float(r[y]) + 0.2 * float(r[x]))
    return lines[: k + 1] + [",".join(r) for r in rows]


BAD = {
    "two axes": (lambda s, t: [s[0], s[1]], "no session for z"),
    "one session": (lambda s, t: [s[0]], "no session for y, z"),
    "two sessions for x": (lambda s, t: [s[0], s[1], s[2], edited(s[0], t, "x2.csv", lambda ls: [
        "# axis: -x" if line.startswith("# axis") else line for line in ls])], "both turn about IMU axis x"),
    "missing raw column": (lambda s, t: [s[0], edited(s[1], t, "y.csv", lambda ls: drop_column(ls, "raw_z")),
                                         s[2]], "missing column 'raw_z'"),
    "no axis line": (lambda s, t: [s[0], s[1], edited(s[2], t, "z.csv", lambda ls: [
        line for line in ls if not line.startswith("# axis")])], "no '# axis:' line"),
    "implausible coupling": (lambda s, t: [edited(s[0], t, "x.csv", askew), s[1], s[2]], "above 10 %"),
}


@pytest.mark.parametrize("case", sorted(BAD))
def test_bad_sessions_fail_with_one_line_and_status_2(case, sessions, tmp_path):
    pick, message = BAD[case]
    work = tmp_path / "work"
    work.mkdir()
    paths = pick(sessions, work)
    out = tmp_path / "imu.yaml"
    one_line_exit_2(run("calibrate", *paths, "-o", out, "--report-dir", tmp_path / "rep"), message)
    assert sorted(p.name for p in tmp_path.iterdir()) == ["work"]


def test_apply_needs_the_three_raw_columns(calibrated, sessions, tmp_path):
    imu, _ = calibrated
    drive = edited(sessions[-1], tmp_path, "drive.csv", lambda ls: drop_column(ls, "raw_y"))
    out = tmp_path / "out.csv"
    one_line_exit_2(run("apply", imu, drive, "-o", out), "missing column 'raw_y'")
    assert not out.exists()


def test_apply_track_bias_learns_each_axis_bias_at_the_vehicles_standstills(calibrated, tmp_path, capsys):
    """A drive of the triad with a turn-on bias on every axis the table never saw: one tracker
    over the three axes learns each at the stops (bias_x/y/z_dps), none while turning."""
    from canical.sim.triad import random_triad

    imu, _ = calibrated
    triad = random_triad(2)
    fs, rng = 100.0, np.random.default_rng(7)
    t = np.arange(0.0, 90.0, 1.0 / fs)
    turn = (t >= 30.0) & (t < 60.0)  # still 0-30 s, turning 30-60 s, still again
    true = np.zeros((t.size, 3))
    true[turn] = np.array([2.0, -1.5, 15.0]) + rng.normal(0.0, 3.0, (int(turn.sum()), 3))
    bias = np.array([0.3, -0.2, 0.25])
    raw = triad.output(t, true + bias, seed=11, fs_hz=fs)
    drive = tmp_path / "drive.csv"
    rows = [f"{a:.2f},{x:.0f},{y:.0f},{z:.0f},25.0" for a, (x, y, z) in zip(t, raw, strict=True)]
    drive.write_text("\n".join(["time_s,raw_x,raw_y,raw_z,temp_c", *rows]) + "\n")
    out = tmp_path / "out.csv"
    assert main(["apply", str(imu), str(drive), "--track-bias", "-o", str(out)]) == 0, capsys.readouterr().err
    assert "standstills used" in capsys.readouterr().out
    cols = read_table(out).columns
    learned = np.array([cols[f"bias_{a}_dps"] for a in "xyz"]).T
    assert np.all(np.abs(learned[-1] - bias) < 0.05), learned[-1]
    assert np.all(np.abs(learned[turn][-1] - learned[turn][0]) < 0.01)  # nothing learned while turning


def test_apply_an_imu_set_to_a_can_log_as_to_the_same_rows_of_a_csv(calibrated, sessions, tmp_path):
    """The multi-axis session's raw values as IMU_RAW frames: the log gives the CSV's rates."""

    import can
    import cantools

    imu, _ = calibrated
    table = read_table(sessions[-1]).columns
    raw = np.column_stack([table[f"raw_{a}"] for a in "xyz"])[:2000]
    dbc = Path(__file__).resolve().parents[2] / "dbc" / "canical.dbc"
    msg = cantools.database.load_file(str(dbc)).get_message_by_name("IMU_RAW")
    log = tmp_path / "imu.log"
    with can.Logger(str(log)) as logger:
        for i, (x, y, z) in enumerate(raw.tolist()):
            data = msg.encode({"GyroRawX": x, "GyroRawY": y, "GyroRawZ": z, "Temperature": 25.0,
                               "Counter": i % 16, "SensorFault": 0})
            logger.on_message_received(can.Message(arbitration_id=msg.frame_id, data=data,
                                                   is_extended_id=False, timestamp=100.0 + i / 200))
    csv = tmp_path / "rows.csv"
    csv.write_text("raw_x,raw_y,raw_z\n" + "".join(f"{x:.0f},{y:.0f},{z:.0f}\n" for x, y, z in raw))
    out_log, out_csv = tmp_path / "from-log.csv", tmp_path / "from-csv.csv"
    assert main(["apply", str(imu), str(log), "--dbc", str(dbc), "-o", str(out_log)]) == 0
    assert main(["apply", str(imu), str(csv), "-o", str(out_csv)]) == 0
    a, b = read_table(out_log).columns, read_table(out_csv).columns
    assert len(a["time_s"]) == 2000
    for name in ("rate_x_dps", "rate_y_dps", "rate_z_dps", "out_of_span_x"):
        assert np.array_equal(a[name], b[name]), name


def write_triad_log(csv_path, log_path) -> None:
    """A triad session CSV as the bus carries it: IMU_RAW with the three raw signals, TABLE_REF
    with the table's rate, axis and mounting, IMU_AUX now and then."""
    from canical.sessions.triad_session import read_triad_session

    write_bus_log(read_triad_session(csv_path), log_path, with_table=True)


def write_bus_log(session, log_path, with_table: bool) -> None:
    """The session's frames in a log: IMU_RAW each sample (just after TABLE_REF, ``with_table``),
    IMU_AUX every tenth."""
    import can
    import cantools

    db = cantools.database.load_file(str(DBC))
    raw_msg, ref_msg, aux_msg = (db.get_message_by_name(n) for n in ("IMU_RAW", "TABLE_REF", "IMU_AUX"))
    axis = session.table_axis
    with can.Logger(str(log_path)) as logger:

        def log(message, stamp: float, values: dict) -> None:
            logger.on_message_received(can.Message(timestamp=stamp, arbitration_id=message.frame_id,
                                                   is_extended_id=False, data=message.encode(values)))

        rows = zip(session.time_s, session.raw.tolist(), session.rate_dps, strict=True)
        for i, (t, raw, rate) in enumerate(rows):
            stamp = 1000.0 + float(t)
            if with_table:
                log(ref_msg, stamp, {"TableRate": float(axis.sign * rate[axis.index]),
                                     "TableAxis": axis.index, "TableSettled": 1,
                                     "TableAxisInverted": int(axis.sign < 0), "TableCounter": i & 0xF})
            if i % 10 == 0:
                log(aux_msg, stamp, {"SupplyVoltage": 12.0, "Uptime": float(t),
                                     "AuxCounter": (i // 10) & 0xF})
            log(raw_msg, stamp + (1e-4 if with_table else 0.0),
                {"GyroRawX": raw[0], "GyroRawY": raw[1], "GyroRawZ": raw[2], "Temperature": 25.0,
                 "Counter": i & 0xF, "SensorFault": 0})


def test_calibrate_from_the_bus_as_from_the_csvs(calibrated, sessions, tmp_path, capsys):
    """The same three sessions (one mounted upside down) as CAN logs: the same IMU set, within
    the last digits; a log whose table does not say its axis is one line, exit 2."""
    imu, _ = calibrated
    logs = []
    for path in sessions[:3]:
        logs.append(tmp_path / f"{path.stem}.log")
        write_triad_log(path, logs[-1])
    out = tmp_path / "from-logs.yaml"
    assert main(["calibrate", *map(str, logs), "--dbc", str(DBC), "-o", str(out)]) == 0, \
        capsys.readouterr().err
    from_logs, from_csvs = imu_set.load(out), imu_set.load(imu)
    assert np.allclose(from_logs.matrix(), from_csvs.matrix(), atol=2e-5)
    assert [c.kind for c in from_logs.axes] == [c.kind for c in from_csvs.axes]

    # The table's rate from a table controller's own frame, which says nothing of the axis.
    dbc = tmp_path / "table.dbc"
    dbc.write_text('VERSION ""\n\nNS_ :\n\nBS_:\n\nBU_: TABLE\n\nBO_ 1536 MYTABLE: 4 TABLE\n'
                   ' SG_ Rate : 0|32@1- (0.0001,0) [-214748.3648|214748.3647] "deg/s" Vector__XXX\n')
    import can
    import cantools

    ref = cantools.database.load_file(str(DBC)).get_message_by_name("TABLE_REF")
    bare = tmp_path / "bare.log"
    with can.Logger(str(bare)) as logger:
        for m in can.LogReader(str(logs[0])):
            if m.arbitration_id == ref.frame_id:
                rate = ref.decode(bytes(m.data))["TableRate"]
                m = can.Message(timestamp=m.timestamp, arbitration_id=1536, is_extended_id=False,
                                data=round(rate / 1e-4).to_bytes(4, "little", signed=True))
            logger.on_message_received(m)
    capsys.readouterr()
    bad = tmp_path / "bad.yaml"
    assert main(["calibrate", str(bare), *map(str, logs[1:]), "--dbc", str(dbc), "--input",
                 "ref_dps=MYTABLE.Rate", "-o", str(bad)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "no TableAxis" in err[0] and not bad.exists(), err


def write_unreferenced_log(csv_path, log_path, table_path, offset_s: float, drift_ppm: float) -> None:
    """A triad session as a bus without the table's frame (IMU_RAW, IMU_AUX) and the table's own
    file: its rate about its own axis at 10 Hz, on its own clock (offset and drift)."""
    from canical.sessions.triad_session import read_triad_session

    session = read_triad_session(csv_path)
    write_bus_log(session, log_path, with_table=False)
    axis = session.table_axis
    own = axis.sign * session.rate_dps[::20, axis.index]  # the table's rate about its own axis
    clock = offset_s + (1.0 + drift_ppm * 1e-6) * session.time_s[::20]
    table_path.write_text("time_s,ref_dps\n" + "".join(f"{t:.6f},{r:.4f}\n" for t, r in zip(clock, own,
                                                                                          strict=True)))


def test_three_axes_from_logs_with_the_tables_own_files(calibrated, sessions, tmp_path, capsys):
    """Issue 33, point 6: a table that logs to its own file, a vendor IMU without TABLE_REF on
    the bus. Each log's turning axis is the raw output that spreads most, its sign (the -y
    session is mounted upside down) from the correlation with the table's rate; --reference
    once per log. The IMU set is the one the CSVs (which carry the table's rate) give."""
    imu, _ = calibrated
    logs, tables = [], []
    for k, path in enumerate(sessions[:3]):
        logs.append(tmp_path / f"{path.stem}.log")
        tables.append(tmp_path / f"{path.stem}-table.csv")
        write_unreferenced_log(path, logs[-1], tables[-1], offset_s=500.0 + 1000.0 * k, drift_ppm=30.0)
    out = tmp_path / "from-tables.yaml"
    refs = [arg for table in tables for arg in ("--reference", str(table))]
    assert main(["calibrate", *map(str, logs), "--dbc", str(DBC), *refs, "-o", str(out)]) == 0, \
        capsys.readouterr().err
    printed = capsys.readouterr().out
    for log, table, axis in zip(logs, tables, ("x", "-y", "z"), strict=True):
        assert f"{log}: the table turns about IMU axis {axis} (raw {axis[-1]} spreads most" in printed
        assert f"reference  {table} on its own clock: offset" in printed
    from_tables, from_csvs = imu_set.load(out), imu_set.load(imu)
    assert np.allclose(from_tables.matrix(), from_csvs.matrix(), atol=2e-4)
    assert [c.kind for c in from_tables.axes] == [c.kind for c in from_csvs.axes]


@pytest.mark.parametrize(("extra", "message"), [
    (["--reference", "t.csv"], "--reference: given 1 time(s) for 3 sessions"),
])
def test_references_must_match_the_logs(sessions, tmp_path, capsys, extra, message):
    logs = [str(tmp_path / f"{k}.log") for k in range(3)]
    assert main(["calibrate", *logs, "--dbc", str(DBC), *extra, "-o", str(tmp_path / "o.yaml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and message in err[0], err


def test_a_reference_for_triad_csvs_is_refused(sessions, tmp_path, capsys):
    refs = [arg for _ in range(3) for arg in ("--reference", "t.csv")]
    assert main(["calibrate", *map(str, sessions[:3]), *refs, "-o", str(tmp_path / "o.yaml")]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "is a CSV, which carries its table's rate" in err[0], err
