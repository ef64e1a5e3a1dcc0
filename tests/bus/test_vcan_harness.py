"""Tests proving the vcan test infrastructure (tests/support/vcan_harness.py, tests/support/vcan_plugin.py).

The ``vcan``-marked tests talk to the kernel's real CAN stack: python-can and raw sockets with
kernel receive filters, two isolated buses, and a CANopen SDO round trip. On a host without
SocketCAN they run inside one User-mode Linux guest and are reported here per test. The
unmarked tests check the harness's own logic on the host.
"""

from __future__ import annotations

import os
import socket
import struct
import subprocess
import sys
import textwrap
import time
from collections.abc import Callable
from pathlib import Path

import pytest

try:
    from support import vcan_harness as harness
    from support import vcan_plugin as plugin
except ImportError:  # pragma: no cover - tests/ imported as a package
    from tests.support import vcan_harness as harness  # type: ignore[no-redef]
    from tests.support import vcan_plugin as plugin  # type: ignore[no-redef]

TESTS_DIR = Path(__file__).resolve().parents[1]
RECV_TIMEOUT = 2.0  # generous: system calls are slow inside UML


# --------------------------------------------------------------------------------------------
# Real SocketCAN (vcan) tests
# --------------------------------------------------------------------------------------------


@pytest.mark.vcan
def test_python_can_send_receive_with_kernel_filters(vcan_channel: str) -> None:
    """Two python-can buses see each other's frames; a filtered bus only gets matching ids."""
    import can

    std_filter = [{"can_id": 0x123, "can_mask": 0x7FF, "extended": False}]
    with (
        can.Bus(interface="socketcan", channel=vcan_channel) as tx,
        can.Bus(interface="socketcan", channel=vcan_channel) as rx_all,
        can.Bus(interface="socketcan", channel=vcan_channel, can_filters=std_filter) as rx_123,
    ):
        sent = [
            can.Message(arbitration_id=0x100, data=[0, 1, 2], is_extended_id=False),
            can.Message(arbitration_id=0x123, data=[1, 0xCA, 0xFE], is_extended_id=False),
            can.Message(arbitration_id=0x124, data=[2], is_extended_id=False),
            can.Message(arbitration_id=0x123, data=[3] * 8, is_extended_id=True),
            can.Message(arbitration_id=0x123, data=[4, 4], is_extended_id=False),
        ]
        for msg in sent:
            tx.send(msg)

        received = [rx_all.recv(timeout=RECV_TIMEOUT) for _ in sent]
        assert all(m is not None for m in received)
        assert [(m.arbitration_id, m.is_extended_id, bytes(m.data)) for m in received] == [
            (m.arbitration_id, m.is_extended_id, bytes(m.data)) for m in sent
        ]

        filtered = []
        while (msg := rx_123.recv(timeout=0.5)) is not None:
            filtered.append(msg)
        # The extended 0x123 must not pass a standard-id filter.
        assert [(m.arbitration_id, m.is_extended_id, m.data[0]) for m in filtered] == [
            (0x123, False, 1),
            (0x123, False, 4),
        ]


@pytest.mark.vcan
def test_raw_socket_kernel_receive_filter(vcan_channel: str) -> None:
    """CAN_RAW_FILTER set with plain sockets: the kernel itself drops non-matching frames."""
    frame = struct.Struct("=IB3x8s")
    with (
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW) as tx,
        socket.socket(socket.AF_CAN, socket.SOCK_RAW, socket.CAN_RAW) as rx,
    ):
        rx.setsockopt(socket.SOL_CAN_RAW, socket.CAN_RAW_FILTER,
                      struct.pack("=II", 0x200, 0x7F0))  # ids 0x200-0x20F
        rx.bind((vcan_channel,))
        tx.bind((vcan_channel,))
        rx.settimeout(RECV_TIMEOUT)
        for can_id in (0x1FF, 0x205, 0x210, 0x20F):
            tx.send(frame.pack(can_id, 2, can_id.to_bytes(2, "big").ljust(8, b"\0")))
        got = [frame.unpack(rx.recv(frame.size))[0] for _ in range(2)]
        assert got == [0x205, 0x20F]
        rx.settimeout(0.3)
        with pytest.raises(TimeoutError):
            rx.recv(frame.size)


@pytest.mark.vcan
def test_vcan_buses_are_isolated(vcan_channels: tuple[str, str]) -> None:
    """Frames on vcan0 never show up on vcan1: tests may use them as two separate buses."""
    import can

    bus0, bus1 = vcan_channels
    with (
        can.Bus(interface="socketcan", channel=bus0) as tx,
        can.Bus(interface="socketcan", channel=bus0) as rx0,
        can.Bus(interface="socketcan", channel=bus1) as rx1,
    ):
        tx.send(can.Message(arbitration_id=0x42, data=b"gyro", is_extended_id=False))
        msg = rx0.recv(timeout=RECV_TIMEOUT)
        assert msg is not None and bytes(msg.data) == b"gyro"
        assert rx1.recv(timeout=0.3) is None


@pytest.mark.vcan
def test_canopen_sdo_round_trip(vcan_channel: str) -> None:
    """A canopen LocalNode serves SDO; a RemoteNode on another socket writes and reads back."""
    import canopen
    from canopen.objectdictionary import UNSIGNED32, VISIBLE_STRING, ODVariable

    def make_od() -> canopen.ObjectDictionary:
        od = canopen.ObjectDictionary()
        for name, index, data_type, default in (("ScaleFactor", 0x2000, UNSIGNED32, 0),
                                                ("Label", 0x2001, VISIBLE_STRING, "")):
            var = ODVariable(name, index)
            var.data_type = data_type
            var.access_type = "rw"
            var.default = default
            od.add_object(var)
        return od

    server_net, client_net = canopen.Network(), canopen.Network()
    server_net.connect(interface="socketcan", channel=vcan_channel)
    try:
        client_net.connect(interface="socketcan", channel=vcan_channel)
        try:
            server = canopen.LocalNode(0x25, make_od())
            server_net.add_node(server)
            written: list[tuple[int, object]] = []
            server.add_write_callback(lambda index, subindex, od, data: written.append(
                (index, data)))
            client = canopen.RemoteNode(0x25, make_od())
            client_net.add_node(client)
            client.sdo.RESPONSE_TIMEOUT = RECV_TIMEOUT

            client.sdo["ScaleFactor"].raw = 0x1234_5678  # expedited transfer
            client.sdo["Label"].raw = "gyro-x scale v1"  # > 4 bytes: segmented transfer
            assert client.sdo["ScaleFactor"].raw == 0x1234_5678
            assert client.sdo["Label"].raw == "gyro-x scale v1"
            assert server.sdo["ScaleFactor"].raw == 0x1234_5678
            assert [index for index, _ in written] == [0x2000, 0x2001]
        finally:
            client_net.disconnect()
    finally:
        server_net.disconnect()


# --------------------------------------------------------------------------------------------
# Harness logic (host only, no vcan needed)
# --------------------------------------------------------------------------------------------


def test_summarize_reports_maps_guest_outcomes() -> None:
    """Guest setup/call/teardown reports collapse to the verdict the host item reports."""

    def rep(when: str, outcome: str, **extra: object) -> dict[str, object]:
        return {"nodeid": "t::x", "when": when, "outcome": outcome, "longrepr": "",
                "sections": [], "skip_reason": None, "wasxfail": None, "duration": 0.5,
                **extra}

    passed = [rep("setup", "passed"), rep("call", "passed"), rep("teardown", "passed")]
    assert plugin.summarize_reports(passed).outcome == "passed"
    assert plugin.summarize_reports(passed).duration == pytest.approx(1.5)

    failed = plugin.summarize_reports([
        rep("setup", "passed"),
        rep("call", "failed", longrepr="E   AssertionError: boom", crash="AssertionError: boom",
            sections=[["Captured stdout call", "hello"]]),
        rep("teardown", "passed"),
    ])
    assert failed.outcome == "failed"
    assert failed.message.splitlines()[0] == "AssertionError: boom [in UML guest, call phase]"
    assert "E   AssertionError: boom" in failed.message
    assert "hello" in failed.message

    skipped = plugin.summarize_reports([rep("setup", "skipped", skip_reason="no FD"),
                                        rep("teardown", "passed")])
    assert (skipped.outcome, skipped.message) == ("skipped", "no FD")

    xfailed = plugin.summarize_reports([rep("setup", "passed"),
                                        rep("call", "skipped", wasxfail="known bug")])
    assert (xfailed.outcome, xfailed.message) == ("xfailed", "known bug")

    teardown_error = plugin.summarize_reports([*passed[:2], rep("teardown", "failed",
                                                                 longrepr="bus left open")])
    assert teardown_error.outcome == "failed" and "teardown phase" in teardown_error.message

    assert plugin.summarize_reports([]).outcome == "missing"


def test_guest_environment_keeps_caller_env_and_isolates_tmp(tmp_path: Path) -> None:
    """PATH, VIRTUAL_ENV, HOME... pass through; temp files and host-only vars do not."""
    base = {"PATH": "/venv/bin:/usr/bin", "VIRTUAL_ENV": "/venv", "HOME": "/home/x",
            "PYTHONPATH": "/src", "TMPDIR": "/host/tmp", "PYTEST_CURRENT_TEST": "t (call)",
            "BASH_FUNC_x%%": "() { :; }"}
    env = harness.guest_environment(base, tmp_path)
    assert env["PATH"] == "/venv/bin:/usr/bin"
    assert env["VIRTUAL_ENV"] == "/venv" and env["HOME"] == "/home/x"
    assert env["PYTHONPATH"] == "/src"
    assert env["TMPDIR"] == str(tmp_path / "tmp")
    assert env[harness.ENV_IN_UML] == "1"
    assert "PYTEST_CURRENT_TEST" not in env and "BASH_FUNC_x%%" not in env


def test_init_script_loads_can_modules_in_dependency_order(tmp_path: Path) -> None:
    """can before can-raw, can-dev before vcan; both vcans come up; status goes to a file."""
    uml = harness.UmlInstallation(kernel=Path("/k"), module_dir=Path("/m"),
                                  insmod=Path("/sbin/insmod"), ip=Path("/sbin/ip"))
    env = harness.guest_environment({"PATH": "/usr/bin"}, tmp_path)
    script, command = harness.render_init_script(uml, tmp_path, ["python", "-c", "print('a b')"],
                                                 tmp_path, env)
    positions = [script.index(f"/m/kernel/{m}") for m in harness.CAN_MODULES]
    assert positions == sorted(positions)
    assert script.index("can-dev.ko") < script.index("vcan.ko")
    for ifname in ("vcan0", "vcan1"):
        assert f"link add dev {ifname} type vcan" in script
    assert "python -c 'print('\"'\"'a b'\"'\"')'" in command
    assert '"$RUN/status"' in command


def test_locate_uml_reports_how_to_install(monkeypatch: pytest.MonkeyPatch) -> None:
    """A missing kernel gives the apt-get command, not a bare FileNotFoundError."""
    monkeypatch.setenv(harness.ENV_KERNEL, "/nonexistent/linux.uml")
    with pytest.raises(harness.UmlUnavailable, match="apt-get install user-mode-linux kmod"):
        harness.locate_uml()
    assert "apt-get install user-mode-linux kmod" in (harness.uml_unavailable_reason() or "")


def _write_inner_suite(tmp_path: Path) -> Path:
    """A tiny project using the plugin, for checking mode decisions in a separate pytest."""
    (tmp_path / "conftest.py").write_text('pytest_plugins = ["support.vcan_plugin"]\n')
    (tmp_path / "test_inner.py").write_text(textwrap.dedent("""
        import pytest

        @pytest.mark.vcan
        def test_needs_bus(vcan_channel):
            assert vcan_channel == "vcan0"

        def test_plain():
            pass
    """))
    return tmp_path


def _run_inner(project: Path, *args: str, **env: str) -> subprocess.CompletedProcess[str]:
    full_env = {k: v for k, v in os.environ.items()
                if not k.startswith(("CANICAL_", "PYTEST_"))}
    full_env.update(PYTHONPATH=os.pathsep.join([str(TESTS_DIR), os.environ.get("PYTHONPATH", "")]),
                    **env)
    return subprocess.run([sys.executable, "-m", "pytest", "-p", "no:cacheprovider", "-rA",
                           "--rootdir", str(project), *args, str(project)],
                          capture_output=True, text=True, env=full_env, timeout=120, check=False)


needs_no_host_vcan = pytest.mark.skipif(
    harness.host_vcan_status(create=False).usable,
    reason="host has SocketCAN: the no-vcan verdict cannot occur here")


@needs_no_host_vcan
def test_no_vcan_and_no_uml_fails_loudly(tmp_path: Path) -> None:
    """Without host vcan and without UML the vcan test FAILS, with the install hint."""
    proc = _run_inner(_write_inner_suite(tmp_path), CANICAL_UML_KERNEL="/nonexistent")
    assert proc.returncode == 1, proc.stdout
    assert "1 failed, 1 passed" in proc.stdout
    assert "apt-get install user-mode-linux kmod" in proc.stdout
    assert "CANICAL_ALLOW_NO_VCAN=1" in proc.stdout


@needs_no_host_vcan
def test_no_vcan_allowed_skips_with_reason(tmp_path: Path) -> None:
    """CANICAL_ALLOW_NO_VCAN=1 turns that failure into a skip that still says why."""
    proc = _run_inner(_write_inner_suite(tmp_path), CANICAL_UML_KERNEL="/nonexistent",
                      CANICAL_ALLOW_NO_VCAN="1")
    assert proc.returncode == 0, proc.stdout
    assert "1 passed, 1 skipped" in proc.stdout
    assert "SKIPPED" in proc.stdout and "User-mode Linux" in proc.stdout


def test_unselected_vcan_tests_boot_nothing(tmp_path: Path) -> None:
    """With the vcan tests deselected, no probing or guest happens at all."""
    proc = _run_inner(_write_inner_suite(tmp_path), "-m", "not vcan",
                      CANICAL_UML_KERNEL="/nonexistent")
    assert proc.returncode == 0, proc.stdout
    assert "1 passed, 1 deselected" in proc.stdout
    assert "vcan:" not in proc.stdout


uml_problem = harness.uml_unavailable_reason()


def uml_selftest(func: Callable[..., None]) -> Callable[..., None]:
    """Mark a test that boots its own guest from the host: part of the vcan tier (so
    ``-m "not vcan"`` boots nothing), not proxied into the session's guest, and skipped only
    where UML is absent (the vcan tests themselves then fail loudly)."""
    func = pytest.mark.skipif(uml_problem is not None, reason=f"no UML: {uml_problem}")(func)
    return pytest.mark.vcan(pytest.mark.uml_selftest(func))


@uml_selftest
def test_run_in_uml_runs_command_with_cwd_env_and_status(tmp_path: Path) -> None:
    """The guest runs our interpreter in our cwd with our env, with vcan0/vcan1 up."""
    code = textwrap.dedent("""
        import os, sys
        from pathlib import Path
        print(os.getcwd(), sys.executable, os.environ["CANICAL_IN_UML"], os.environ["MARKER"])
        print(sorted(p.name for p in Path("/sys/class/net").iterdir()))
        print("to stderr", file=sys.stderr)
        sys.exit(3)
    """)
    workdir = tmp_path / "work"
    workdir.mkdir()
    result = harness.run_in_uml([sys.executable, "-c", code], cwd=workdir,
                                env=dict(os.environ, MARKER="m-42"), run_dir=tmp_path / "run",
                                timeout=120)
    assert result.returncode == 3, result.describe()
    first, second = result.stdout.splitlines()[:2]
    assert first == f"{workdir} {sys.executable} 1 m-42"
    assert "vcan0" in second and "vcan1" in second
    assert result.stderr.strip() == "to stderr"
    assert (tmp_path / "run" / "stdout.txt").read_text() == result.stdout


def _processes_mentioning(text: str) -> list[int]:
    pids = []
    for proc in Path("/proc").iterdir():
        try:
            if proc.name.isdigit() and text in (proc / "cmdline").read_text(errors="replace"):
                pids.append(int(proc.name))
        except OSError:
            continue
    return pids


@uml_selftest
def test_run_in_uml_timeout_kills_the_whole_guest(tmp_path: Path) -> None:
    """A hung guest command is cut off at the timeout and leaves no UML processes behind."""
    run_dir = tmp_path / "run"
    start = time.monotonic()
    result = harness.run_in_uml(["sleep", "300"], run_dir=run_dir, timeout=4)
    assert result.timed_out and result.returncode is None
    assert time.monotonic() - start < 30
    assert "timed out" in result.describe()
    time.sleep(0.2)
    assert _processes_mentioning(str(run_dir)) == []


@uml_selftest
def test_guest_cannot_change_the_host(tmp_path: Path) -> None:
    """The host's / is read-only under a tmpfs overlay: the guest's writes outside its run dir
    (a host file, a new file in /etc, removing a file) stay in the guest, halting leaves the
    host's wtmp alone, and only the run dir carries results back."""
    host_file = tmp_path / "host.txt"
    host_file.write_text("host")
    marker = Path("/etc") / f"canical-guest-{tmp_path.name}"
    wtmp = Path("/var/log/wtmp")
    wtmp_before = wtmp.read_bytes() if wtmp.exists() else None
    script = (f"echo guest > {host_file} && touch {marker} && rm {host_file} && "
              f"echo in-guest > $CANICAL_UML_RUN_DIR/out.txt")
    result = harness.run_in_uml(["sh", "-c", script], run_dir=tmp_path / "run", timeout=120)
    assert result.returncode == 0, result.describe()
    assert host_file.read_text() == "host"
    assert not marker.exists()
    assert (tmp_path / "run" / "out.txt").read_text() == "in-guest\n"
    assert (wtmp.read_bytes() if wtmp.exists() else None) == wtmp_before
