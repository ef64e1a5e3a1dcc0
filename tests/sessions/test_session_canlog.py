"""CAN logs as sessions: a turntable session recorded from the bus calibrates directly."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import can
import numpy as np
import pytest
from support.daemon_fixtures import DBC, write_config, write_sets

from canical.errors import CanicalError
from canical.frames.codec import load_dbc
from canical.sessions.canlog import default_inputs, read_canlog
from canical.sessions.canlog_format import is_canlog
from canical.sessions.csv_file import format_session, read_table
from canical.sets import coefficient_file
from canical.sim.gyro import GyroModel
from canical.sim.sessions import paper_rates, sweep_session

T0 = 1_700_000_000.0
# One recording per format python-can writes and reads, compressed ones too.
FORMATS = (".log", ".asc", ".blf", ".trc", ".csv", ".db", ".mf4", ".asc.gz", ".trc.gz", ".log.gz")


@pytest.fixture(scope="module")
def turntable(tmp_path_factory: pytest.TempPathFactory):
    """A short turntable session on axis z as CSV and as .log/.asc/.blf of the same frames."""
    folder = tmp_path_factory.mktemp("canlog")
    session = sweep_session(GyroModel(), paper_rates(step=6.0), dwell_s=4.0, seed=4, sensor="IMU-0001",
                            aux={"temp_c": lambda t, w, rng: 25.0 + 0.01 * t})
    db = load_dbc(DBC)
    raw, aux, ref = (db.get_message_by_name(n) for n in ("IMU_RAW", "IMU_AUX", "TABLE_REF"))
    msgs = []
    for i, (t, r, w, temp) in enumerate(zip(session.time_s, session.raw, session.ref_dps,
                                            session.aux["temp_c"], strict=True)):
        stamp = T0 + float(t)
        msgs.append(can.Message(timestamp=stamp, arbitration_id=ref.frame_id, is_extended_id=False,
                                data=ref.encode({"TableRate": float(w), "TableAxis": 2, "TableSettled": 1,
                                                 "TableAxisInverted": 0, "TableCounter": i & 0xF})))
        if i % 10 == 0:
            msgs.append(can.Message(timestamp=stamp, arbitration_id=aux.frame_id, is_extended_id=False,
                                    data=aux.encode({"SupplyVoltage": 5.0, "Uptime": 60.0 + float(t),
                                                     "AuxCounter": 0})))
        msgs.append(can.Message(timestamp=stamp, arbitration_id=raw.frame_id, is_extended_id=False,
                                data=raw.encode({"GyroRawX": 12, "GyroRawY": -7, "GyroRawZ": int(r),
                                                 "Temperature": round(float(temp), 1), "Counter": i & 0xF,
                                                 "SensorFault": 0})))
    msgs.insert(5, can.Message(timestamp=T0, arbitration_id=raw.frame_id, is_extended_id=False,
                               data=bytes(3)))  # a damaged frame: dropped, like the daemon does
    paths = {}
    for suffix in FORMATS:
        paths[suffix] = folder / f"bus{suffix}"
        with can.Logger(str(paths[suffix])) as logger:
            if isinstance(logger, can.SqliteWriter):  # python-can 4.6 drops what is queued past 500 at stop
                logger.MAX_BUFFER_SIZE_BEFORE_WRITES = logger.MAX_TIME_BETWEEN_WRITES = float("inf")
            for m in msgs:
                logger.on_message_received(m)
    csv = folder / "session.csv"
    csv.write_text(format_session(session))
    return session, paths, csv, folder


def _canical(*args: str, cwd: Path) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "canical", *args], capture_output=True, text=True, cwd=cwd,
                          timeout=300, check=False)


@pytest.mark.parametrize("suffix", FORMATS)
def test_every_log_format_gives_the_recorded_session(turntable, suffix: str) -> None:
    session, paths, _, _ = turntable
    log = read_canlog(paths[suffix], dbc=DBC, axis="z", inputs=default_inputs(DBC))
    s = log.session
    assert log.table_axis == "z" and log.dropped == 1 and log.skipped == 0
    np.testing.assert_array_equal(s.raw, session.raw)
    np.testing.assert_allclose(s.ref_dps, session.ref_dps, atol=1e-4)
    np.testing.assert_allclose(s.time_s, session.time_s, atol=2e-6)
    assert set(s.aux) == {"Temperature", "SupplyVoltage"}
    np.testing.assert_allclose(s.aux["Temperature"], session.aux["temp_c"], atol=0.05 + 1e-9)


def test_calibrate_from_a_can_log_equals_calibrate_from_csv(turntable) -> None:
    """Same samples, same set: axis taken from the table's TableAxis, reference held per frame."""
    _, paths, csv, folder = turntable
    a = _canical("calibrate", str(paths[".log"]), "--dbc", str(DBC), "--no-extend", "--segments", "3",
                 "--order", "2", "--sensor", "IMU-0001", "-o", "from-log.yaml", cwd=folder)
    assert a.returncode == 0, a.stderr
    b = _canical("calibrate", str(csv), "--no-extend", "--segments", "3", "--order", "2", "--axis", "z",
                 "-o", "from-csv.yaml", cwd=folder)
    assert b.returncode == 0, b.stderr
    from_log = coefficient_file.load(folder / "from-log.yaml")
    from_csv = coefficient_file.load(folder / "from-csv.yaml")
    assert from_log.axis == "z" and from_log.sensor_id == "IMU-0001"
    assert from_log.v0 == pytest.approx(from_csv.v0, abs=1e-9)
    np.testing.assert_allclose(from_log.model.coefficients, from_csv.model.coefficients, atol=1e-6)


def test_a_python_can_csv_log_is_told_from_a_session_csv(turntable) -> None:
    _, paths, csv, _ = turntable
    assert is_canlog(paths[".csv"]) and not is_canlog(csv)
    assert all(is_canlog(p) for p in paths.values())


@pytest.mark.parametrize("suffix", [".trc", ".asc.gz", ".mf4", ".db", ".csv"])
def test_calibrate_reads_every_format_as_the_candump_log(turntable, suffix: str) -> None:
    """A PEAK trace or a compressed log used to be taken for a session CSV; now it is the same session."""
    from canical.commands.cli import main

    _, paths, _, folder = turntable
    sets = {}
    for fmt in (".log", suffix):
        out = folder / f"cal{fmt}.yaml"
        code = main(["calibrate", str(paths[fmt]), "--dbc", str(DBC), "--no-extend", "--segments", "3",
                     "--order", "2", "--sensor", "IMU-0001", "-o", str(out)])
        assert code == 0
        sets[fmt] = coefficient_file.load(out)
    assert sets[suffix].axis == "z"
    assert sets[suffix].v0 == pytest.approx(sets[".log"].v0, abs=1e-9)
    np.testing.assert_allclose(sets[suffix].model.coefficients, sets[".log"].model.coefficients,
                               atol=1e-6)


def test_mf4_without_asammdf_is_one_line_naming_the_extra(turntable, monkeypatch, capsys) -> None:
    from canical.commands.cli import main

    _, paths, _, folder = turntable
    monkeypatch.setitem(sys.modules, "asammdf", None)  # import asammdf now raises ImportError
    with pytest.raises(CanicalError, match=r"asammdf: pip install 'canical\[mf4\]'"):
        read_canlog(paths[".mf4"], dbc=DBC, axis="z", inputs={})
    out = folder / "no-mf4.yaml"
    assert main(["calibrate", str(paths[".mf4"]), "--dbc", str(DBC), "-o", str(out)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1 and "canical[mf4]" in err[0] and ".mf4" in err[0]
    assert not out.exists()
    assert main(["record", "-o", str(folder / "r.mf4"), "--interface", "virtual", "--channel", "x",
                 "--dbc", str(DBC)]) == 2
    assert "canical[mf4]" in capsys.readouterr().err


@pytest.mark.parametrize("suffix", [".log", ".trc", ".mf4", ".asc.gz"])
def test_apply_on_a_can_log_uses_the_daemon_mapping(turntable, tmp_path: Path, suffix: str) -> None:
    """With --config, the inputs come from the signals the daemon configuration names."""
    _, paths, _, _ = turntable
    sets = write_sets(tmp_path)
    config = write_config(tmp_path, "can0")
    out = tmp_path / "z.csv"
    proc = _canical("apply", str(sets["x"]), str(paths[suffix]), "--config", str(config), "-o", str(out),
                    cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    table = read_table(out)
    assert table.header == ["time_s", "raw", "temp_c", "rate_dps", "out_of_span"]
    assert table.meta["axis"] == "x" and table.meta["sensor"] == "IMU-0001"
    np.testing.assert_array_equal(table.columns["raw"], 12.0)
    np.testing.assert_allclose(table.columns["time_s"][:3], [60.0, 60.0, 60.0])  # Uptime, held


def test_can_log_errors_are_one_line_and_write_nothing(turntable, tmp_path: Path) -> None:
    _, paths, _, _ = turntable
    sets = write_sets(tmp_path)
    cases = [
        ((str(sets["z"]), str(paths[".log"])), "needs --dbc or --config"),
        ((str(sets["x"]), str(paths[".log"]), "--dbc", str(DBC)), "needs input(s) temp_c, time_s"),
        ((str(sets["z"]), str(tmp_path / "none.log"), "--dbc", str(DBC)), "file not found"),
        ((str(sets["z"]), str(paths[".log"]), "--dbc", str(DBC), "--input", "t=IMU_RAW"), "NAME=MESSAGE"),
    ]
    for args, message in cases:
        out = tmp_path / "out.csv"
        proc = _canical("apply", *args, "-o", str(out), cwd=tmp_path)
        assert proc.returncode == 2, proc.stderr
        assert message in proc.stderr and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
        assert not out.exists()
    damaged = tmp_path / "damaged.blf"
    damaged.write_bytes(paths[".blf"].read_bytes()[:300])
    proc = _canical("calibrate", str(damaged), "--dbc", str(DBC), "-o", str(tmp_path / "s.yaml"),
                    cwd=tmp_path)
    assert proc.returncode == 2 and len(proc.stderr.strip().splitlines()) == 1, proc.stderr
    assert not (tmp_path / "s.yaml").exists()


@pytest.mark.parametrize("suffix", [".log", ".blf", ".trc.gz", ".mf4", ".csv"])
def test_record_writes_a_log_that_calibrate_reads(turntable, tmp_path: Path, suffix: str) -> None:
    """canical record on a (virtual) bus keeps the IMU's and the table's frames, drops others,
    and the log it writes (in the format its suffix names) reads back as the session that was sent."""
    import threading

    from canical.commands.cli import main

    session, paths, _, _ = turntable
    sent = [m for m in can.LogReader(str(paths[".log"])) if len(m.data) == 8][:3000]
    n_raw = sum(m.arbitration_id == 0x190 for m in sent)

    def play() -> None:
        with can.Bus(interface="virtual", channel=f"record-test{suffix}") as bus:
            time.sleep(0.5)
            bus.send(can.Message(arbitration_id=0x555, data=b"noise", is_extended_id=False))
            for m in sent:
                bus.send(m)

    player = threading.Thread(target=play)
    player.start()
    out = tmp_path / f"rec{suffix}"
    code = main(["record", "-o", str(out), "--interface", "virtual", "--channel", f"record-test{suffix}",
                 "--dbc", str(DBC), "--frames", str(n_raw), "--duration", "60"])
    player.join()
    assert code == 0
    got = list(can.LogReader(str(out)))
    assert [m.arbitration_id for m in got] == [m.arbitration_id for m in sent[: len(got)]]  # no 0x555
    assert sum(m.arbitration_id == 0x190 for m in got) == n_raw
    log = read_canlog(out, dbc=DBC, axis="z", inputs={})
    np.testing.assert_array_equal(log.session.raw, session.raw[: len(log.session.raw)])


def test_record_refuses_formats_it_cannot_write_safely(tmp_path: Path, capsys) -> None:
    from canical.commands.cli import main

    for name, message in (("rec.db", "does not write .db"), ("rec.txt", "must end in one of")):
        out = tmp_path / name
        assert main(["record", "-o", str(out), "--interface", "virtual", "--channel", "x",
                     "--dbc", str(DBC)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and message in err[0], err
        assert not out.exists()


def test_asammdf_is_imported_only_when_an_mf4_is_named() -> None:
    """python-can imports asammdf (seconds: pandas, sympy) at ``import can``; canical's commands
    skip it unless an argument is an MDF4 file, so the daemon and push start fast with canical[mf4]."""
    probe = ("import sys; from canical.commands.cli import skip_mdf4_import; skip_mdf4_import(sys.argv[1:]); "
             "import can; print(sys.modules.get('asammdf') is not None)")
    for arg, loaded in (("drive.log", "False"), ("drive.MF4", "True"), ("drive.mf4.gz", "True")):
        proc = subprocess.run([sys.executable, "-c", probe, "calibrate", arg], capture_output=True, text=True,
                              timeout=120, check=True)
        assert proc.stdout.strip() == loaded, (arg, proc.stdout, proc.stderr)


def test_the_gyro_and_table_signals_can_be_named(turntable) -> None:
    """``--input raw=`` and ``--input ref_dps=`` name the signals: the same set as canical's defaults."""
    from canical.commands.cli import main

    _, paths, _, folder = turntable
    common = ["--no-extend", "--segments", "3", "--order", "2", "--sensor", "IMU-0001", "--axis", "z"]
    log = str(paths[".log"])
    assert main(["calibrate", log, "--dbc", str(DBC), *common, "-o", str(folder / "d.yaml")]) == 0
    assert main(["calibrate", log, "--dbc", str(DBC), "--input", "raw=IMU_RAW.GyroRawZ",
                 "--input", "ref_dps=TABLE_REF.TableRate", *common, "-o", str(folder / "n.yaml")]) == 0
    default, named = (coefficient_file.load(folder / f) for f in ("d.yaml", "n.yaml"))
    assert named.v0 == pytest.approx(default.v0, abs=1e-6)


@pytest.mark.parametrize("suffix", [".log", ".blf", ".asc.gz"])
def test_a_log_read_in_blocks_is_the_whole_session(turntable, suffix: str) -> None:
    """Any block size gives, joined, the rows read_canlog holds, bit for bit, and the same counts."""
    from canical.sessions.canlog import stream_canlog

    _, paths, _, _ = turntable
    inputs = {**default_inputs(DBC), "time_s": "IMU_AUX.Uptime"}
    for mapping in (default_inputs(DBC), inputs):
        whole = read_canlog(paths[suffix], dbc=DBC, axis="z", inputs=mapping, ref=None)
        for rows in (1, 7, 500, 10**6):
            stream = stream_canlog(paths[suffix], dbc=DBC, axis="z", inputs=mapping, rows_per_block=rows)
            blocks = list(stream.blocks())
            assert all(len(b.raw) <= rows for b in blocks) and len(blocks) == -(-len(whole.session) // rows)
            s = whole.session
            assert stream.meta == s.meta and stream.channels == list(s.aux)
            assert np.concatenate([b.time_s for b in blocks]).tobytes() == s.time_s.tobytes()
            assert np.concatenate([b.raw for b in blocks]).tobytes() == s.raw.tobytes()
            for name, values in s.aux.items():
                assert np.concatenate([b.aux[name] for b in blocks]).tobytes() == values.tobytes()
            assert (stream.frames, stream.skipped) == (whole.frames, whole.skipped)


@pytest.mark.parametrize("axis", ["x", "y", "z"])
def test_apply_on_a_log_in_blocks_writes_the_whole_logs_bytes(turntable, tmp_path: Path, monkeypatch,
                                                              axis: str) -> None:
    """apply reads a log a block at a time, the terms' state carried across: any block size writes
    the bytes the whole log corrected at once writes."""
    from canical.commands.cli import main
    from canical.sessions import canlog
    from canical.sets.corrector import Corrector

    _, paths, _, _ = turntable
    sets = write_sets(tmp_path)
    config = write_config(tmp_path, "can0")

    def apply(out: Path) -> bytes:
        args = ["apply", str(sets[axis]), str(paths[".log"]), "--config", str(config), "-o", str(out)]
        assert main(args) == 0
        return out.read_bytes()

    with monkeypatch.context() as whole_log:  # the whole log held and corrected at once
        whole_log.setattr(Corrector, "elementwise_model", property(lambda self: False))
        expected = apply(tmp_path / "whole.csv")
    assert expected.count(b"\n") > 1000
    for rows in (1, 13, 256, 10**6):
        monkeypatch.setattr(canlog, "BLOCK_ROWS", rows)
        assert apply(tmp_path / f"blocks-{rows}.csv") == expected
