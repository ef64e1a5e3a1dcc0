"""The daemon with field_log: one record per standstill decision and per power-on, written as
closed segments at each status period; a restart continues the power-on count, a reload of the
sets is not a power-on; a bad section is refused at start in one line. In-process, no vcan."""

from __future__ import annotations

from pathlib import Path

import can
import pytest
from support.daemon_fixtures import write_config, write_sets
from test_daemon_bias_tracking import SETTINGS, drive_frames
from test_daemon_compiled import feed

from canical.bus.daemon import Daemon
from canical.bus.daemon_config import load_config
from canical.errors import CanicalError
from canical.fieldlog import segments
from canical.fieldlog.record import ADOPTED, POWER_ON, FieldRecord

FIELD_LOG = {"dir": "field", "max_mb": 1, "vehicle_id": "veh-0001"}


class NoBus:
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        pass


def read(folder: Path) -> list[FieldRecord]:
    lines: list[str] = []
    paths = segments.segment_paths(folder)
    found = [r for s in segments.read_segments(paths, lines.append) for r in s.records]
    assert lines == []
    return found


def run(config_path: Path, msgs: list[can.Message]) -> Daemon:
    daemon = Daemon(load_config(config_path), compiled=False)
    daemon.load_sets()
    feed(daemon, msgs, NoBus())
    assert daemon.tracking is not None
    daemon.tracking.finish()  # what the daemon's stop does
    daemon.tracking.log_events()
    daemon.tracking.flush()
    return daemon


def test_each_standstill_decision_and_power_on_is_a_record_per_axis(tmp_path: Path) -> None:
    write_sets(tmp_path)
    config = write_config(tmp_path, "trk", bias_tracking=SETTINGS, field_log=FIELD_LOG)
    daemon = run(config, drive_frames())
    records = read(tmp_path / "field")
    assert {r.axes for r in records} == {("x",), ("y",), ("z",)}
    z = [r for r in records if r.axes == ("z",)]
    # the turn is driving (no record); the standstill after it ends with the daemon's stop
    assert [r.decision for r in z] == [POWER_ON, ADOPTED, ADOPTED]
    assert all(r.vehicle_id == "veh-0001" and r.set_id == daemon.sets.combined_id and r.power_on == 0
               for r in records)
    assert all(abs(r.bias_dps[0] - 0.3) < 0.05 for r in z[1:])
    assert z[1].temp_c is not None and 25.0 < z[1].temp_c < 30.0
    assert 20.0 < z[1].since_power_on_s < 24.0 and z[0].utc < z[1].utc < z[2].utc  # Uptime from 3 s
    assert records[0].sensor_id == daemon.sets.axes[2].corrector.cset.sensor_id  # type: ignore[union-attr]


def test_a_flush_with_nothing_new_writes_nothing_and_a_restart_is_a_new_power_on(tmp_path: Path) -> None:
    write_sets(tmp_path)
    config = write_config(tmp_path, "trk", bias_tracking=SETTINGS, field_log=FIELD_LOG)
    first = run(config, drive_frames(25.0))
    before = [(p.name, p.stat().st_mtime_ns) for p in segments.segment_paths(tmp_path / "field")]
    assert first.tracking is not None
    first.tracking.log_events()
    first.tracking.flush()
    assert [(p.name, p.stat().st_mtime_ns) for p in segments.segment_paths(tmp_path / "field")] == before
    run(config, drive_frames(25.0))
    counts = sorted({r.power_on for r in read(tmp_path / "field")})
    assert counts == [0, 1] and len(segments.segment_paths(tmp_path / "field")) == 2


def test_a_reload_of_the_sets_is_not_a_power_on(tmp_path: Path) -> None:
    write_sets(tmp_path)
    config = write_config(tmp_path, "trk", bias_tracking=SETTINGS, field_log=FIELD_LOG)
    daemon = run(config, drive_frames(25.0))
    write_sets(tmp_path, variant=1)
    daemon.load_sets()
    feed(daemon, drive_frames(25.0, seed=6), NoBus())
    assert daemon.tracking is not None
    daemon.tracking.log_events()
    daemon.tracking.flush()
    records = read(tmp_path / "field")
    assert [r.power_on for r in records if r.decision == POWER_ON] == [0, 0, 0]  # one per axis, at start
    assert len({r.set_id for r in records}) == 2


@pytest.mark.parametrize(("section", "message"), [
    ({"max_mb": 1, "vehicle_id": "v"}, "field_log.dir: missing or not a file path"),
    ({"dir": "f", "vehicle_id": "v", "max_mb": 0}, "field_log.max_mb: must be a number of megabytes"),
    ({"dir": "f", "vehicle_id": "a b"}, "field_log.vehicle_id: must be the vehicle's id"),
    ({"dir": "f", "vehicle_id": "v", "size": 1}, "field_log.size: unknown key"),
    ("f", "field_log: must be a mapping"),
])
def test_a_bad_section_is_refused_at_start_in_one_line(tmp_path: Path, section: object, message: str) -> None:
    write_sets(tmp_path)
    with pytest.raises(CanicalError) as info:
        load_config(write_config(tmp_path, "bad", bias_tracking=SETTINGS, field_log=section))
    assert message in str(info.value) and "\n" not in str(info.value)


def test_a_field_log_without_bias_tracking_is_refused(tmp_path: Path) -> None:
    write_sets(tmp_path)
    with pytest.raises(CanicalError, match="field_log: needs bias_tracking"):
        load_config(write_config(tmp_path, "bad", field_log=FIELD_LOG))


def test_apply_with_the_daemon_configuration_writes_the_daemons_records(tmp_path: Path) -> None:
    """apply LOG --config CONFIG --track-bias --field-log DIR: the records the daemon wrote for the
    axis, decision for decision (the set id is the set's own, the time the log's)."""
    from canical.commands.cli import main

    write_sets(tmp_path)
    config = write_config(tmp_path, "trk", bias_tracking=SETTINGS, field_log=FIELD_LOG)
    msgs = drive_frames()
    log = tmp_path / "drive.log"
    with can.Logger(str(log)) as logger:
        for m in msgs:
            logger.on_message_received(m)
    run(config, msgs)
    offline = tmp_path / "offline"
    assert main(["apply", str(tmp_path / "imu-z.yaml"), str(log), "--config", str(config), "--track-bias",
                 "-o", str(tmp_path / "z.csv"), "--field-log", str(offline), "--vehicle-id", "veh-0001",
                 "--drive-start", "2026-11-27T08:00:00Z"]) == 0

    def essence(r: FieldRecord) -> tuple:
        return (r.decision, r.power_on, r.since_power_on_s, r.temp_c, r.bias_dps, r.sigma_dps, r.reason)

    daemon_z = [essence(r) for r in read(tmp_path / "field") if r.axes == ("z",)]
    assert [essence(r) for r in read(offline)] == daemon_z and len(daemon_z) == 3


def test_serve_check_says_where_the_field_log_goes(tmp_path: Path,
                                                   capsys: pytest.CaptureFixture[str]) -> None:
    from canical.commands.cli import main

    write_sets(tmp_path)
    config = write_config(tmp_path, "trk", bias_tracking=SETTINGS, field_log=FIELD_LOG)
    assert main(["serve", "--config", str(config), "--check"]) == 0
    assert f"field log: {tmp_path / 'field'} for vehicle veh-0001, at most 1 MB" in capsys.readouterr().out
    assert not (tmp_path / "field").exists()  # checked, not made
