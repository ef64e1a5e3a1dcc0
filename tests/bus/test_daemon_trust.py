"""The daemon with ``trust:``: only sets the lab signed for this sensor, never an older one.

In-process, as the other reload tests run the daemon (``test_daemon_imu_set``): a set refused for
its signature is refused exactly as a corrupt set is, at start, on a file change and on SIGHUP (a
forced reload): one warning line, the running set kept, and no frame corrected by the refused
set (every frame sent after it carries the running set's tag). A newer signed set is adopted.
Without ``trust:`` the daemon works as before and warns once, at start, that sets are not
authenticated.
"""

from __future__ import annotations

import logging
import shutil
import subprocess
import sys
from collections.abc import Callable
from pathlib import Path

import can
import numpy as np
import pytest
from support.daemon_fixtures import (
    ALL_TERMS,
    AXES,
    DBC,
    imu_set_config,
    imu_stream,
    write_config,
    write_imu_set,
    write_sets,
)
from support.sighup_operator import Offer, run_with_operator
from support.signed_sets import REFUSALS, Lab, edit, make_lab, refused_case, signed_copy
from test_daemon_compiled import StandInSocket, kernel_frame, serve_socket
from test_daemon_imu_set import LSB, expected, messages, sent_rates
from test_daemon_reload_stress import PacedSocket

from canical.bus.daemon import Daemon
from canical.bus.daemon_config import load_config
from canical.bus.link import SocketLink
from canical.bus.reloads import Reload
from canical.errors import CanicalError
from canical.files.atomic_file import write_text_atomic
from canical.frames.codec import load_dbc
from canical.sets.coefficient_file import content_crc

#: A set signed by the lab for the sensor the configuration names, but whose content is another
#: sensor's: the daemon's sensor check refuses it as it refuses an unsigned one.
CASES = {**REFUSALS, "signed-for-another-sensor": "configured sensor is IMU-0001"}


@pytest.fixture(scope="module")
def lab(tmp_path_factory) -> Lab:
    return make_lab(tmp_path_factory.mktemp("keys"))


def trust(lab: Lab, require: bool = True) -> dict:
    return {"keys": [str(lab.pub)], "require": require}


def offered(case: str, src: Path, folder: Path, lab: Lab) -> Path:
    """``src`` made into the refused ``case`` while version 2 runs."""
    if case != "signed-for-another-sensor":
        return refused_case(case, src, folder, lab, version=2)
    dst = folder / f"unsigned-{case}-{src.name}"
    shutil.copyfile(src, dst)

    def other(content: dict) -> None:
        for axis in [content, *content.get("axes", {}).values()]:
            if "sensor" in axis:
                axis["sensor"]["id"] = "IMU-0002"

    edit(dst, other, recompute_crc=True)
    return signed_copy(dst, folder / f"{case}-{src.name}", lab.key, 3)


def refusals(caplog: pytest.LogCaptureFixture) -> list[str]:
    return [r.getMessage() for r in caplog.records if r.levelno == logging.WARNING]


# -- per-axis sets ------------------------------------------------------------------------------


@pytest.fixture(scope="module")
def axis_sets(tmp_path_factory) -> tuple[dict[str, Path], dict[str, Path]]:
    """Two generations of per-axis sets (unsigned): the running one and a newer one."""
    folder = tmp_path_factory.mktemp("axis-sets")
    (folder / "next").mkdir()
    return write_sets(folder), write_sets(folder / "next", variant=1)


@pytest.fixture
def signed_axes(axis_sets, lab: Lab, tmp_path: Path) -> Path:
    """A configuration with ``trust:`` running the first generation, each axis signed as version 2."""
    for path in axis_sets[0].values():
        signed_copy(path, tmp_path / path.name, lab.key, 2)
    return write_config(tmp_path, "trust", trust=trust(lab))


@pytest.mark.parametrize("force", [False, True], ids=["file changed", "SIGHUP"])
@pytest.mark.parametrize("case", sorted(CASES))
def test_a_set_not_signed_for_this_sensor_or_rolled_back_is_refused_on_reload(
        case, force, signed_axes, axis_sets, lab, tmp_path, caplog) -> None:
    daemon = Daemon(load_config(signed_axes), compiled=False)
    daemon.load_sets()
    running = daemon.sets
    assert running.complete and [a.version for a in running.axes] == [2, 2, 2]
    (tmp_path / "next").mkdir()
    bad = offered(case, axis_sets[1]["z"], tmp_path / "next", lab)
    caplog.clear()
    write_text_atomic(tmp_path / "imu-z.yaml", bad.read_text())
    daemon._reload(force=force, why="test")
    assert [a.set_id for a in daemon.sets.axes] == [a.set_id for a in running.axes]
    assert daemon.sets.axes[2].corrector is running.axes[2].corrector
    lines = refusals(caplog)
    assert len(lines) == 1 and lines[0].startswith("axis z: ") and CASES[case] in lines[0], lines
    assert "keeping set" in lines[0] and "\n" not in lines[0]


def test_a_newer_signed_set_is_adopted_and_an_older_one_then_refused(signed_axes, axis_sets, lab, tmp_path,
                                                                     caplog) -> None:
    daemon = Daemon(load_config(signed_axes), compiled=False)
    daemon.load_sets()
    first = daemon.sets
    (tmp_path / "next").mkdir()
    newer = signed_copy(axis_sets[1]["z"], tmp_path / "next" / "z.yaml", lab.key, 5)
    write_text_atomic(tmp_path / "imu-z.yaml", newer.read_text())
    daemon._reload(force=False, why="test")
    assert daemon.sets.axes[2].set_id != first.axes[2].set_id and daemon.sets.axes[2].version == 5
    assert daemon.sets.axes[2].reloads == 1
    # the set that ran before, signed as version 2, is now a rollback
    write_text_atomic(tmp_path / "imu-z.yaml", signed_copy(axis_sets[0]["z"], tmp_path / "old.yaml",
                                                           lab.key, 2).read_text())
    caplog.clear()
    daemon._reload(force=True, why="test")
    assert daemon.sets.axes[2].version == 5 and "rollback" in " ".join(refusals(caplog))


@pytest.mark.parametrize("case", ["unsigned", "untrusted", "tampered-crc-recomputed"])
def test_at_start_a_refused_set_leaves_its_axis_uncalibrated(case, signed_axes, axis_sets, lab, tmp_path,
                                                             caplog) -> None:
    (tmp_path / "next").mkdir()
    write_text_atomic(tmp_path / "imu-z.yaml",
                      offered(case, axis_sets[0]["z"], tmp_path / "next", lab).read_text())
    daemon = Daemon(load_config(signed_axes), compiled=False)
    with caplog.at_level(logging.INFO):
        daemon.load_sets()
    assert daemon.sets.axes[2].corrector is None and daemon.sets.axes[0].corrector is not None
    assert any(line.startswith("axis z: ") and REFUSALS[case] in line for line in refusals(caplog))
    assert not any("not authenticated" in line for line in refusals(caplog))


def test_without_trust_the_daemon_warns_once_at_start(axis_sets, tmp_path, caplog) -> None:
    for path in axis_sets[0].values():
        shutil.copyfile(path, tmp_path / path.name)
    daemon = Daemon(load_config(write_config(tmp_path, "plain")), compiled=False)
    with caplog.at_level(logging.INFO):
        daemon.load_sets()
        write_text_atomic(tmp_path / "imu-z.yaml", axis_sets[1]["z"].read_text())
        daemon._reload(force=True, why="test")
    assert daemon.sets.complete and daemon.sets.axes[2].reloads == 1  # unsigned sets are used as before
    assert sum("sets are not authenticated" in line for line in refusals(caplog)) == 1


def test_trust_not_required_warns_and_adopts(axis_sets, lab, tmp_path, caplog) -> None:
    for path in axis_sets[0].values():
        shutil.copyfile(path, tmp_path / path.name)
    daemon = Daemon(load_config(write_config(tmp_path, "soft", trust=trust(lab, require=False))),
                    compiled=False)
    with caplog.at_level(logging.INFO):
        daemon.load_sets()
    assert daemon.sets.complete and all(a.version is None for a in daemon.sets.axes)
    assert sum("not signed" in r.getMessage() and "trust.require is false" in r.getMessage()
               for r in caplog.records) == 3


@pytest.mark.parametrize(("trust_section", "message"), [
    ({"keys": []}, "trust.keys: must be a list"),
    ({"keys": ["missing.pub"]}, "trust.keys[0]: "),
    ({"keys": ["lab.key"]}, "trust.keys[0]: "),
    ({"keys": ["lab.pub"], "require": "yes"}, "trust.require: must be true or false"),
    ({"keys": ["lab.pub"], "when": 1}, "trust.when: unknown key"),
])
def test_a_bad_trust_section_is_one_line_naming_the_key(trust_section, message, axis_sets, lab,
                                                         tmp_path) -> None:
    for path in (lab.key, lab.pub, *axis_sets[0].values()):
        shutil.copyfile(path, tmp_path / path.name)
    (tmp_path / "lab.key").chmod(0o600)
    with pytest.raises(CanicalError) as refused:
        load_config(write_config(tmp_path, "bad", trust=trust_section))
    assert message in str(refused.value) and "\n" not in str(refused.value)


def test_serve_check_verifies(signed_axes, axis_sets, tmp_path) -> None:
    def check() -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "canical", "serve", "--config", str(signed_axes),
                               "--check"], capture_output=True, text=True, timeout=120, check=False)

    ok = check()
    assert ok.returncode == 0 and "configuration OK" in ok.stdout and "not authenticated" not in ok.stdout
    assert ok.stdout.count("signed by a trusted key as version 2") == 3
    shutil.copyfile(axis_sets[0]["y"], tmp_path / "imu-y.yaml")  # unsigned
    bad = check()
    assert bad.returncode == 2 and "not signed" in bad.stderr
    assert len(bad.stderr.strip().splitlines()) == 1 and "Traceback" not in bad.stderr


# -- an IMU set, with frames ---------------------------------------------------------------------


@pytest.fixture(scope="module")
def imu_sets(tmp_path_factory) -> tuple[Path, Path]:
    folder = tmp_path_factory.mktemp("imu-sets")
    (folder / "next").mkdir()
    return (write_imu_set(folder, terms=ALL_TERMS),
            write_imu_set(folder / "next", terms=ALL_TERMS, variant=1,
                          coupling=((0.998, -0.01, 0.006), (0.009, 1.003, -0.012), (0.017, -0.004, 0.999))))


def frames(n: int, seed: int) -> list[tuple[bytes, float]]:
    stream = imu_stream(n, seed=seed)
    return [(kernel_frame(can.Message(arbitration_id=fid, data=data, is_extended_id=False)), 100.0 + i * 1e-3)
            for i, (fid, data) in enumerate(stream.frames)]


@pytest.mark.parametrize("case", sorted(CASES))
def test_no_frame_is_corrected_by_a_refused_imu_set(case, imu_sets, lab, tmp_path, caplog) -> None:
    signed_copy(imu_sets[0], tmp_path / "imu-set.yaml", lab.key, 2)
    daemon = Daemon(load_config(imu_set_config(tmp_path, "imu", trust=trust(lab))))
    daemon.load_sets()
    running = daemon.sets
    assert running.complete and running.coupling is not None
    msgs, signals = messages(200)
    cut = [k for k, m in enumerate(msgs) if m.arbitration_id == 0x190][100]  # raw frame 100
    stream = [(kernel_frame(m), m.timestamp) for m in msgs]
    sock = StandInSocket(daemon, stream[:cut])
    serve_socket(daemon, sock)
    (tmp_path / "next").mkdir()
    bad = offered(case, imu_sets[1], tmp_path / "next", lab)
    write_text_atomic(tmp_path / "imu-set.yaml", bad.read_text())
    caplog.clear()
    daemon._running = True
    daemon._reload(force=False, why="test")
    lines = refusals(caplog)
    assert len(lines) == 1 and lines[0].startswith("imu set: ") and CASES[case] in lines[0], lines
    sock.frames = iter(stream[cut:])
    serve_socket(daemon, sock)
    rates, tags = sent_rates(sock.sent)
    assert len(tags) == 200 and set(tags) == {running.tag}
    assert daemon.sets.combined_id == running.combined_id
    # every frame's rates are the running set's, as apply computes them (the tag alone is 4 bits)
    want, _ = expected(imu_sets[0], signals)
    inside = np.abs(want).max(axis=1) < 327.0  # the frame saturates at its signals' range
    assert inside.sum() > 150 and np.abs(rates - want)[inside].max() <= LSB / 2 + 1e-9


def test_a_newer_signed_imu_set_is_adopted_between_two_frames(imu_sets, lab, tmp_path) -> None:
    signed_copy(imu_sets[0], tmp_path / "imu-set.yaml", lab.key, 2)
    daemon = Daemon(load_config(imu_set_config(tmp_path, "imu", trust=trust(lab))))
    daemon.load_sets()
    old = daemon.sets
    sock = StandInSocket(daemon, frames(100, seed=3))
    serve_socket(daemon, sock)
    write_text_atomic(tmp_path / "imu-set.yaml",
                      signed_copy(imu_sets[1], tmp_path / "new.yaml", lab.key, 3).read_text())
    daemon._running = True
    daemon._reload(force=True, why="test")
    sock.frames = iter(frames(100, seed=4))
    serve_socket(daemon, sock)
    _, tags = sent_rates(sock.sent)
    # (the 4-bit tags of two sets are equal one time in 16: the sets' ids differ always)
    assert tags == [old.tag] * 100 + [daemon.sets.tag] * 100 and daemon.sets.combined_id != old.combined_id
    assert [a.version for a in daemon.sets.axes] == [3, 3, 3]


def test_the_keys_signed_content_covers_every_axis(imu_sets) -> None:
    """The IMU set's canonical content (what is signed) holds each axis's model: a signature over
    it covers all three axes and the coupling (the CRC's bytes, the same ones)."""
    import yaml

    content = yaml.safe_load(imu_sets[0].read_text())
    assert sorted(content["axes"]) == list(AXES) and int(content["crc32"], 16) == content_crc(content)


def test_through_the_real_loop_and_sighup_a_refused_set_corrects_no_frame(imu_sets, lab, tmp_path,
                                                                          caplog) -> None:
    """``Daemon.run`` (receive loop, reload worker thread, the SIGHUP handler) while frames stream:
    an operator thread offers a tampered set (CRC recomputed) with SIGHUP, then a newer signed one.
    Every frame before the newer set's adoption carries the running set's tag, every one after it
    the newer one's: the tampered set corrected none."""
    signed_copy(imu_sets[0], tmp_path / "imu-set.yaml", lab.key, 2)
    config = load_config(imu_set_config(tmp_path, "hup", trust=trust(lab), watch_period_s=3600.0,
                                        status_period_s=0.05))
    daemon: Daemon
    sock: PacedSocket
    daemon = Daemon(config, open_link=lambda channel, matches: SocketLink(sock))  # type: ignore[arg-type]
    sock = PacedSocket(daemon, frames(2400, seed=5))
    done: list[tuple[int, Reload]] = []
    adopt = daemon._adopt

    def recording_adopt(reload: Reload) -> None:
        adopt(reload)
        done.append((daemon.stats.frames_in, reload))

    daemon._adopt = recording_adopt  # type: ignore[method-assign]
    (tmp_path / "next").mkdir()
    tampered = offered("tampered-crc-recomputed", imu_sets[1], tmp_path / "next", lab)
    newer = signed_copy(imu_sets[1], tmp_path / "newer.yaml", lab.key, 3)

    def offer(path: Path) -> Callable[[], None]:
        return lambda: write_text_atomic(tmp_path / "imu-set.yaml", path.read_text())

    def reloads(k: int) -> Callable[[], bool]:
        return lambda: sum(r.why == "SIGHUP" for _, r in done) >= k

    with caplog.at_level(logging.INFO):
        run_with_operator(daemon, [Offer(600 * k, offer(path), reloads(k), f"reload {k}")
                                   for k, path in enumerate((tampered, newer), start=1)])
    hups = [(n, r) for n, r in done if r.why == "SIGHUP"]
    assert len(hups) == 2
    (_, refused), (switch, adopted) = hups
    assert refused.new.combined_id == refused.base.combined_id  # the running set carried on
    assert any("imu set: " in m.text and "does not match the content" in m.text and m.refused
               for m in refused.messages)
    assert adopted.new.combined_id != adopted.base.combined_id and daemon.sets is adopted.new
    rate_id = load_dbc(DBC).get_message_by_name("CANICAL_RATE").frame_id
    _, tags = sent_rates([payload for can_id, payload in sock.sent if can_id == rate_id])
    assert len(tags) == 2400
    assert tags == [refused.base.tag] * switch + [adopted.new.tag] * (len(tags) - switch)
