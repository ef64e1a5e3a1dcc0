"""``push --dry-run`` at the desk: the bus unreachable, what can be checked is checked and said."""

from __future__ import annotations

from pathlib import Path

from support.imu_fixtures import imu_set

from canical.commands.cli import main
from canical.sets import coefficient_file


def test_a_dry_run_without_a_bus_checks_the_sets_and_says_what_it_could_not(tmp_path: Path, capsys) -> None:
    path = tmp_path / "z.yaml"
    coefficient_file.save(path, imu_set("z"))
    args = ["push", str(path), "--node", "0x10", "--interface", "socketcan", "--channel", "canical-none"]
    assert main([*args, "--dry-run"]) == 0
    out = capsys.readouterr().out.splitlines()
    assert out[0].startswith("push (dry run, offline): the bus is not reachable (cannot open CAN interface")
    assert out[1].startswith(f"  axis z: set 0x{coefficient_file.set_crc(imu_set('z')):08x} from {path}")
    assert out[1].endswith("fits its evaluator")
    assert "its serial number against the sets' sensor id" in out[2] and out[2].endswith("nothing written")
    assert main(args) == 2  # a real push needs the device
    assert "cannot open CAN interface" in capsys.readouterr().err
