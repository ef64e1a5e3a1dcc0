"""When plateau finding finds nothing or too little, `calibrate` says what it saw and what to change.

Every message is one line on stderr, exit status 2, no traceback.
"""

import json

import can
import numpy as np
import pytest
from support.daemon_fixtures import DBC
from support.sessions import write_session

from canical.commands.cli import main
from canical.frames.codec import load_dbc
from canical.sessions.session import Session
from canical.sim.gyro import GyroModel
from canical.sim.sessions import paper_rates, sweep_session
from canical.sim.table_recording import TableBehaviour

SEEN = ("longest steady stretch", "reference noise", "deg/s (tolerance", "rate changes")


def _calibrate_error(capsys, path, *extra: str) -> str:
    capsys.readouterr()
    assert main(["calibrate", str(path), "-o", str(path.with_suffix(".yaml")), "--no-extend", *extra]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and err.startswith("canical calibrate: error: "), err
    assert "Traceback" not in err
    assert not path.with_suffix(".yaml").exists()
    return err


def _session(tmp_path, rates, name="s.csv", **kw):
    kw.setdefault("dwell_s", 3.0)
    kw.setdefault("fs_hz", 50.0)
    return write_session(tmp_path / name, sweep_session(GyroModel(), np.asarray(rates, float), **kw))


def test_short_plateaus_name_min_plateau(tmp_path, capsys):
    path = _session(tmp_path, paper_rates(step=10.0), dwell_s=0.9)
    err = _calibrate_error(capsys, path)
    assert "no constant-rate plateau found" in err
    assert all(s in err for s in SEEN)
    assert "--min-plateau below 1 s would accept" in err
    # ...and the option does change the outcome.
    assert main(["calibrate", str(path), "-o", str(tmp_path / "ok.yaml"), "--no-extend",
                 "--min-plateau", "0.3", "--settle", "0.1"]) == 0


def test_a_reference_noisier_than_the_tolerance_names_rate_tol(tmp_path, capsys):
    table = TableBehaviour(accel_dps2=10.0, reference="measured", jitter_dps=0.05)
    path = _session(tmp_path, paper_rates(step=10.0), table=table)
    err = _calibrate_error(capsys, path, "--rate-tol", "0.0001")
    assert "no constant-rate plateau found" in err and all(s in err for s in SEEN)
    assert "reference noise 0.05" in err or "reference noise 0.04" in err
    assert "a larger --rate-tol than 0.0001 deg/s" in err
    # Auto tolerance (from the estimated noise) finds them.
    assert main(["calibrate", str(path), "-o", str(tmp_path / "ok.yaml"), "--no-extend"]) == 0


def test_too_few_rates_says_what_was_seen(tmp_path, capsys):
    err = _calibrate_error(capsys, _session(tmp_path, [0.0, 10.0, 20.0, 0.0, 10.0], fs_hz=200.0))
    assert "only 3 distinct plateau rates (at least 4 are needed)" in err and all(s in err for s in SEEN)


def test_no_zero_rate_plateau(tmp_path, capsys):
    err = _calibrate_error(capsys, _session(tmp_path, [5.0, 10.0, 20.0, 30.0, 40.0]))
    assert "no zero-rate plateau among 5 plateaus (V0 cannot be measured)" in err
    assert all(s in err for s in SEEN)


def test_a_settled_flag_that_never_rises_is_named(tmp_path, capsys):
    session = sweep_session(GyroModel(), paper_rates(step=10.0), dwell_s=3.0, fs_hz=50.0,
                            table=TableBehaviour(accel_dps2=10.0, settled_flag=True))
    never = Session(session.time_s, session.raw, session.ref_dps, session.aux, session.meta,
                    settled=np.zeros(len(session), dtype=bool))
    path = write_session(tmp_path / "flag.csv", never)
    err = _calibrate_error(capsys, path, "--settled-column", "settled")
    assert "steady rows flagged not settled by the table" in err
    assert "settled flag (--settled-column, TABLE_REF.TableSettled)" in err
    # The honest flag is accepted, and a missing flag column is named.
    honest = write_session(tmp_path / "ok.csv", session)
    assert main(["calibrate", str(honest), "-o", str(tmp_path / "ok.yaml"), "--no-extend",
                 "--settled-column", "settled"]) == 0
    err = _calibrate_error(capsys, path, "--settled-column", "table_ok")
    assert "missing column 'table_ok'" in err


def test_time_backwards_in_a_csv_names_the_line(tmp_path, capsys):
    path = _session(tmp_path, paper_rates(step=10.0))
    lines = path.read_text().splitlines()
    lines[10], lines[11] = lines[11], lines[10]
    path.write_text("\n".join(lines) + "\n")
    err = _calibrate_error(capsys, path)
    assert "line 12: time_s goes backwards" in err  # 1-based: lines[11] is line 12


def test_time_backwards_in_a_can_log_names_the_frame(tmp_path, capsys):
    db = load_dbc(DBC)
    raw, aux, ref = (db.get_message_by_name(n) for n in ("IMU_RAW", "IMU_AUX", "TABLE_REF"))
    path = tmp_path / "back.log"
    stamps = [100.0, 100.01, 100.02, 100.015, 100.03]
    with can.Logger(str(path)) as logger:
        for i, stamp in enumerate(stamps):
            logger.on_message_received(can.Message(
                timestamp=stamp, arbitration_id=ref.frame_id, is_extended_id=False,
                data=ref.encode({"TableRate": 0.0, "TableAxis": 2, "TableSettled": 1, "TableAxisInverted": 0,
                                 "TableCounter": i})))
            logger.on_message_received(can.Message(
                timestamp=stamp, arbitration_id=aux.frame_id, is_extended_id=False,
                data=aux.encode({"SupplyVoltage": 5.0, "Uptime": stamp, "AuxCounter": 0})))
            logger.on_message_received(can.Message(
                timestamp=stamp, arbitration_id=raw.frame_id, is_extended_id=False,
                data=raw.encode({"GyroRawX": 0, "GyroRawY": 0, "GyroRawZ": 5, "Temperature": 25.0,
                                 "Counter": i, "SensorFault": 0})))
    err = _calibrate_error(capsys, path, "--dbc", str(DBC), "--axis", "z")
    assert "frame 12: timestamp goes backwards (100.015000 after 100.020000)" in err


@pytest.mark.parametrize(("option", "value", "says"), [
    ("--rate-tol", "fast", "--rate-tol must be 'auto' or a number of deg/s"),
    ("--settle", "-1", "--settle must be a finite number of seconds, 0 or more"),
    ("--min-plateau", "nan", "--min-plateau must be a finite number of seconds"),
])
def test_bad_threshold_values_are_refused(tmp_path, capsys, option, value, says):
    with pytest.raises(SystemExit) as exc:
        main(["calibrate", "s.csv", "-o", "c.yaml", option, value])
    assert exc.value.code == 2
    assert says in capsys.readouterr().err


def test_options_are_in_help(capsys):
    with pytest.raises(SystemExit):
        main(["calibrate", "--help"])
    out = capsys.readouterr().out
    for option in ("--min-plateau S", "--settle S", "--rate-tol DPS", "--settled-column NAME", "[auto]"):
        assert option in out


def test_the_report_says_what_plateau_finding_estimated(tmp_path, capsys):
    table = TableBehaviour(accel_dps2=3.0, reference="measured", jitter_dps=0.03, ref_rate_hz=10.0,
                           asynchronous=True)
    path = _session(tmp_path, paper_rates(step=10.0), table=table)
    assert main(["calibrate", str(path), "-o", str(tmp_path / "c.yaml"), "--no-extend",
                 "--report-dir", str(tmp_path / "rep")]) == 0
    assert "plateaus   reference noise 0.0" in capsys.readouterr().out
    found = json.loads((tmp_path / "rep" / "report.json").read_text())["plateau_finding"]
    assert found["reference_noise_dps"] == pytest.approx(0.03, rel=0.3)
    assert found["reference_update_s"] == pytest.approx(0.1, rel=0.05)
    assert found["end_guard_s"] >= 0.1
    assert "- plateau finding: reference noise 0.0" in (tmp_path / "rep" / "report.md").read_text()


@pytest.mark.parametrize(("accel", "ref_hz"), [(2.0, 10.0)])
def test_a_continuous_sweep_is_told_apart_from_a_noisy_reference(tmp_path, capsys, accel: float,
                                                                 ref_hz: float) -> None:
    """A table sweeping continuously (its encoder's rate, exact) faster than its 10 Hz reference
    can follow (0.2 deg/s per update): refused with advice for a sweep (record steps), not a
    larger --rate-tol (the reference is not noisy). The same sweep at 0.5 deg/s² with a 100 Hz
    reference is calibrated (tests/calibrate/test_sweep.py)."""
    fs = 100.0
    t = np.arange(0.0, 240.0, 1.0 / fs)
    ref = 60.0 - np.abs((accel * t) % 240.0 - 120.0)  # -60 up to 60 and back, at ``accel``
    held = ref[(np.floor(t * ref_hz) / ref_hz * fs).astype(int)]  # the encoder's updates, held
    gyro = GyroModel()
    raw = np.round(gyro.output(t, ref, rng=np.random.default_rng(1), fs_hz=fs))
    path = write_session(tmp_path / "sweep.csv", Session(time_s=t, raw=raw, ref_dps=held,
                                                          meta={"sensor": "SIM-1", "axis": "z"}))
    err = _calibrate_error(capsys, path)
    assert "the reference never stands still" in err and "continuous sweep, not a noisy reference" in err
    assert "too coarse or slow for it: 0.2 deg/s between updates" in err
    assert "record the rates as steps" in err
    assert "--rate-tol" not in err
