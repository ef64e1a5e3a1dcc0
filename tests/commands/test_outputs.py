"""Outputs a command cannot write: one line naming the path, exit status 2, nothing written.

Each command's outputs are checked before it writes any, staged while it runs and moved into
place together (canical/files/output_plan.py); a full disk mid-write leaves nothing behind.
"""

import errno
import os
import subprocess
import sys
import uuid
from pathlib import Path

import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st
from support.sessions import write_session

from canical.commands.cli import main
from canical.errors import CanicalError
from canical.files import output_plan as plan_module
from canical.files.atomic_file import write_text_atomic
from canical.files.output_plan import output_plan
from canical.sim.sessions import paper_session

DBC = str(Path(__file__).resolve().parents[2] / "dbc" / "canical.dbc")


@pytest.fixture(scope="module")
def session_csv(tmp_path_factory):
    return write_session(tmp_path_factory.mktemp("s") / "session.csv", paper_session(seed=5))


@pytest.fixture(scope="module")
def coeffs(session_csv, tmp_path_factory):
    path = tmp_path_factory.mktemp("c") / "c.yaml"
    assert main(["calibrate", str(session_csv), "-o", str(path), "--no-extend"]) == 0
    return path


def files_under(folder: Path) -> list[str]:
    return sorted(str(p.relative_to(folder)) for p in folder.rglob("*"))


def one_line_error(capsys, command: str, path: str) -> str:
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1, err
    assert err.startswith(f"canical {command}: error: cannot write {path}: "), err
    return err


@pytest.mark.parametrize("target", ["/proc/foo.yaml", "/nonexistent-dir/foo.yaml", "DIR"])
def test_calibrate_unwritable_output(target, session_csv, tmp_path, capsys):
    target = str(tmp_path) if target == "DIR" else target
    assert main(["calibrate", str(session_csv), "-o", target]) == 2
    reason = one_line_error(capsys, "calibrate", target)
    if target == str(tmp_path):
        assert reason.endswith("it is a folder")


@pytest.mark.parametrize("option", ["--report", "--report-dir"])
def test_calibrate_leaves_no_set_when_its_report_cannot_be_written(option, session_csv, tmp_path, capsys):
    ok = tmp_path / "ok.yaml"
    bad = "/proc/r.json" if option == "--report" else "/proc/rep"
    assert main(["calibrate", str(session_csv), "-o", str(ok), option, bad]) == 2
    one_line_error(capsys, "calibrate", bad)
    assert files_under(tmp_path) == []


def test_report_dir_below_a_file_is_refused(session_csv, tmp_path, capsys):
    (tmp_path / "plain").write_text("x")
    assert main(["calibrate", str(session_csv), "-o", str(tmp_path / "ok.yaml"),
                 "--report-dir", str(tmp_path / "plain" / "rep")]) == 2
    one_line_error(capsys, "calibrate", str(tmp_path / "plain" / "rep"))
    assert files_under(tmp_path) == ["plain"]


@pytest.mark.parametrize("target", ["/proc/foo.csv", "DIR", "/nonexistent-dir/out.csv"])
def test_apply_unwritable_output(target, coeffs, session_csv, tmp_path, capsys):
    target = str(tmp_path) if target == "DIR" else target
    assert main(["apply", str(coeffs), str(session_csv), "-o", target]) == 2
    one_line_error(capsys, "apply", target)


def test_demo_unwritable_folder(tmp_path, capsys):
    assert main(["demo", "--out", "/proc/demo", "--no-bus"]) == 2
    one_line_error(capsys, "demo", "/proc/demo")
    (tmp_path / "file").write_text("x")
    assert main(["demo", "--out", str(tmp_path / "file"), "--no-bus"]) == 2
    assert "exists and is not a folder" in one_line_error(capsys, "demo", str(tmp_path / "file"))


def test_record_unwritable_output(capsys):
    args = ["record", "--interface", "virtual", "--channel", f"t-{uuid.uuid4().hex}", "--dbc", DBC]
    assert main([*args, "-o", "/proc/x.log", "--duration", "0.1"]) == 2
    one_line_error(capsys, "record", "/proc/x.log")


def test_record_writes_its_log_only_at_the_end(tmp_path, capsys):
    out = tmp_path / "x.log"
    args = ["record", "--interface", "virtual", "--channel", f"t-{uuid.uuid4().hex}", "--dbc", DBC]
    assert main([*args, "-o", str(out), "--duration", "0.2"]) == 0
    assert files_under(tmp_path) == ["x.log"]


def test_pull_checks_every_output_before_touching_the_bus(tmp_path, capsys):
    # No device answers on this bus: the output error must come first, without a timeout.
    args = ["pull", "--node", "0x10", "--interface", "virtual", "--channel", f"t-{uuid.uuid4().hex}"]
    assert main([*args, "-o", "/proc/imu-{axis}.yaml"]) == 2
    one_line_error(capsys, "pull", "/proc/imu-x.yaml")


def test_no_traceback_in_a_real_process(session_csv, tmp_path):
    run = subprocess.run(
        [sys.executable, "-m", "canical", "calibrate", str(session_csv), "-o", str(tmp_path / "ok.yaml"),
         "--report", "/proc/r.json"],
        capture_output=True, text=True, timeout=120,
    )
    assert run.returncode == 2
    assert run.stderr == "canical calibrate: error: cannot write /proc/r.json: cannot create a file in " \
        "/proc (No such file or directory)\n"
    assert files_under(tmp_path) == []


def test_full_disk_mid_write_leaves_nothing(session_csv, tmp_path, capsys, monkeypatch):
    """ENOSPC as a file system reports it when the data reach the disk (at fsync)."""
    previous = tmp_path / "ok.yaml"
    previous.write_text("previous set\n")
    calls = []

    def fsync(fd: int) -> None:
        calls.append(fd)
        if len(calls) == 3:  # the set and report.json went through; the disk fills on the next
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))

    monkeypatch.setattr(plan_module.os, "fsync", fsync)
    status = main(["calibrate", str(session_csv), "-o", str(previous), "--report", str(tmp_path / "r.json"),
                   "--report-dir", str(tmp_path / "rep")])
    assert status == 2
    err = capsys.readouterr().err
    assert err.startswith(f"canical calibrate: error: cannot write {tmp_path / 'rep'}/"), err
    assert err.endswith(": No space left on device\n") and err.count("\n") == 1, err
    assert files_under(tmp_path) == ["ok.yaml"]
    assert previous.read_text() == "previous set\n"


@pytest.fixture
def tiny_disk(tmp_path):
    """A 32 KiB tmpfs (needs root and mount): a real full disk."""
    mount = tmp_path / "disk"
    mount.mkdir()
    done = subprocess.run(["mount", "-t", "tmpfs", "-o", "size=32k", "tmpfs", str(mount)],
                          capture_output=True, text=True)
    if done.returncode != 0:
        pytest.skip(f"cannot mount a tmpfs here: {done.stderr.strip()}")
    try:
        yield mount
    finally:
        subprocess.run(["umount", str(mount)], check=True)


def test_full_tmpfs_leaves_nothing(session_csv, tiny_disk, capsys):
    status = main(["calibrate", str(session_csv), "-o", str(tiny_disk / "ok.yaml"),
                   "--report-dir", str(tiny_disk / "rep")])
    assert status == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "No space left on device" in err, err
    assert files_under(tiny_disk) == []


# --- the mechanism itself ---------------------------------------------------------------------

good_names = st.sampled_from(["a.txt", "b.csv", "sub/c.json", "sub/deeper/d.yaml"])
bad_targets = st.sampled_from(["/proc/x.txt", "/nonexistent-dir/x", "FILE/below", "FOLDER"])


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.function_scoped_fixture])
@given(names=st.lists(good_names, min_size=1, max_size=4, unique=True),
       bad=st.one_of(st.none(), bad_targets), fail_after=st.booleans())
def test_all_or_nothing(tmp_path, names, bad, fail_after):
    """Every file appears at the end of a clean run; a bad output or an error: nothing at all."""
    root = tmp_path / uuid.uuid4().hex
    root.mkdir()
    (root / "FILE").write_text("x")
    (root / "FOLDER").mkdir()
    before = files_under(root)
    files = [root / n for n in names if "/" not in n]
    folders = [root / "sub"] if any("/" in n for n in names) else []
    bad_path = None if bad is None else (bad if bad.startswith("/") else str(root / bad))
    try:
        with output_plan(*files, bad_path, dirs=folders):
            for n in names:
                write_text_atomic(root / n, n)
            if fail_after:
                raise RuntimeError("the command failed after writing")
    except CanicalError as exc:
        assert bad is not None and str(exc).startswith(f"cannot write {bad_path}: ")
    except RuntimeError:
        assert fail_after
    else:
        assert bad is None and not fail_after
        folders_made = {str(p) for n in names for p in Path(n).parents} - {"."}
        assert files_under(root) == sorted({*before, *names, *folders_made})
        assert all((root / n).read_text() == n for n in names)
        return
    assert files_under(root) == before


def test_apply_on_a_full_tmpfs_leaves_nothing(coeffs, session_csv, tiny_disk, capsys):
    assert main(["apply", str(coeffs), str(session_csv), "-o", str(tiny_disk / "out.csv")]) == 2
    err = capsys.readouterr().err
    assert err == f"canical apply: error: cannot write {tiny_disk / 'out.csv'}: No space left on device\n"
    assert files_under(tiny_disk) == []


def test_demo_on_a_full_tmpfs_leaves_nothing(tiny_disk, capsys):
    assert main(["demo", "--out", str(tiny_disk / "demo"), "--no-bus"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"canical demo: error: cannot write {tiny_disk / 'demo'}/"), err
    assert err.endswith(": No space left on device\n") and err.count("\n") == 1, err
    assert files_under(tiny_disk) == []


def test_noise_leaves_no_plot_when_its_json_cannot_be_written(tmp_path, capsys):
    rng = np.random.default_rng(3)
    t = np.arange(20_000) / 100.0
    record = tmp_path / "static.csv"
    record.write_text("time_s,rate_dps\n" + "".join(f"{a:.3f},{b:.6f}\n" for a, b in
                                                     zip(t, 0.05 * rng.standard_normal(t.size), strict=True)))
    plot = tmp_path / "adev.png"
    assert main(["noise", str(record), "--plot", str(plot), "--json", "/proc/noise.json"]) == 2
    one_line_error(capsys, "noise", "/proc/noise.json")
    assert files_under(tmp_path) == ["static.csv"]


@pytest.mark.parametrize("target", ["/proc/imu.dcf", "/nonexistent-dir/imu.dcf", "DIR"])
def test_export_unwritable_output(target, tmp_path, capsys):
    from support.imu_fixtures import imu_sets

    from canical.sets import coefficient_file

    paths = []
    for axis, cset in imu_sets().items():
        paths.append(str(tmp_path / f"imu-{axis}.yaml"))
        coefficient_file.save(paths[-1], cset)
    target = str(tmp_path) if target == "DIR" else target
    assert main(["export", "dcf", *paths, "-o", target]) == 2
    one_line_error(capsys, "export", target)
    assert not any(p.endswith(".dcf") for p in files_under(tmp_path))


@pytest.fixture
def umask():
    """Set the process's umask for one test, and put the old one back."""
    old = os.umask(0o022)
    yield os.umask
    os.umask(old)


@pytest.mark.parametrize(("mask", "mode"), [(0o022, 0o644), (0o027, 0o640), (0o077, 0o600)])
def test_written_files_take_the_users_umask(mask, mode, umask, session_csv, tmp_path):
    """A set written into /etc/canical under umask 022 is readable by the service's user (it was
    0600 whatever the umask: tempfile.mkstemp's mode), and 077 still keeps it private."""
    umask(mask)
    assert plan_module.user_file_mode() == mode
    out, report = tmp_path / "z.yaml", tmp_path / "report"
    assert main(["calibrate", str(session_csv), "-o", str(out), "--no-extend",
                 "--report-dir", str(report)]) == 0
    written = [out, *(p for p in report.rglob("*") if p.is_file())]
    assert len(written) > 2
    assert {p.name: p.stat().st_mode & 0o777 for p in written} == {p.name: mode for p in written}
    write_text_atomic(tmp_path / "plain.txt", "x")  # outside a command's plan
    assert (tmp_path / "plain.txt").stat().st_mode & 0o777 == mode
