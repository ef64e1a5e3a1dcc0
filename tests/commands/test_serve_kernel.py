"""``serve`` on a kernel without SocketCAN: one line, exit 2, what to do; not retries forever.

An interface that is down comes back and the daemon waits for it; a kernel without AF_CAN never
will (the daemon used to log "still down after 240 s (125 reopen attempts)" without end).
"""

from __future__ import annotations

import errno
import socket
import subprocess
import sys
import time
from pathlib import Path

import pytest
from support.daemon_fixtures import write_config, write_sets

from canical.commands import serve
from canical.commands.cli import main


def no_af_can(monkeypatch: pytest.MonkeyPatch) -> None:
    real = socket.socket

    def refuse(family=-1, *args, **kwargs):
        if family == getattr(socket, "AF_CAN", object()):
            raise OSError(errno.EAFNOSUPPORT, "Address family not supported by protocol")
        return real(family, *args, **kwargs)

    monkeypatch.setattr(socket, "socket", refuse)


@pytest.fixture
def config(tmp_path: Path) -> Path:
    write_sets(tmp_path)
    return write_config(tmp_path, "can0")


def test_serve_refuses_a_kernel_without_socketcan_in_one_line(monkeypatch, config: Path, capsys) -> None:
    no_af_can(monkeypatch)
    start = time.monotonic()
    assert main(["serve", "--config", str(config)]) == 2
    assert time.monotonic() - start < 5
    err = capsys.readouterr().err.strip()
    assert err == (f"canical serve: error: {config}: bus.interface socketcan: this kernel has no SocketCAN "
                   "(socket(AF_CAN): Address family not supported by protocol): load its modules "
                   "(modprobe can-raw; and vcan for a virtual bus), or name a python-can interface "
                   "that works here in bus.interface")


def test_check_warns_but_passes_on_such_a_kernel(monkeypatch, config: Path, capsys) -> None:
    """--check checks the configuration, which may be meant for the vehicle, not this machine."""
    no_af_can(monkeypatch)
    assert main(["serve", "--config", str(config), "--check"]) == 0
    captured = capsys.readouterr()
    assert captured.err == ""
    assert captured.out.splitlines()[-2].endswith("configuration OK (socketcan can0)")
    assert captured.out.splitlines()[-1].startswith(
        "note: serve would not start on this machine: this kernel has no SocketCAN")


def test_another_interface_is_not_probed(monkeypatch, tmp_path: Path) -> None:
    no_af_can(monkeypatch)
    write_sets(tmp_path)
    cfg = write_config(tmp_path, "v0", interface="virtual")
    assert serve.socketcan_missing() is not None
    from canical.bus.daemon_config import load_config
    assert load_config(cfg).interface == "virtual"


@pytest.mark.skipif(serve.socketcan_missing() is None, reason="this kernel has SocketCAN")
def test_the_real_kernel_here_gets_the_same_answer(config: Path) -> None:
    proc = subprocess.run([sys.executable, "-m", "canical", "serve", "--config", str(config)],
                          capture_output=True, text=True, timeout=60)
    assert proc.returncode == 2
    assert len(proc.stderr.strip().splitlines()) == 1 and "modprobe can-raw" in proc.stderr
