"""A CANopen IMU without canical's firmware: told apart before anything is read or written."""

from __future__ import annotations

from pathlib import Path

import canopen
import pytest
import yaml
from support.daemon_fixtures import write_sets

from canical.commands.cli import main


def foreign_od() -> canopen.ObjectDictionary:
    """A vendor's node: an identity object and nothing of canical's."""
    od = canopen.ObjectDictionary()
    identity = canopen.objectdictionary.ODRecord("Identity object", 0x1018)
    for sub, (name, value) in enumerate((("Highest sub-index", 4), ("Vendor-ID", 0x0000ABCD),
                                         ("Product code", 0x42), ("Revision", 1), ("Serial", 7))):
        var = canopen.objectdictionary.ODVariable(name, 0x1018, sub)
        types = canopen.objectdictionary
        var.data_type = types.UNSIGNED8 if sub == 0 else types.UNSIGNED32
        var.default = value
        identity.add_member(var)
    od.add_object(identity)
    return od


@pytest.fixture
def foreign(request):
    channel = f"foreign-{request.node.name}"
    network = canopen.Network()
    network.connect(interface="virtual", channel=channel, receive_own_messages=False)
    network.add_node(canopen.LocalNode(8, foreign_od()))
    yield channel
    network.disconnect()


def one_line(capsys) -> str:
    err = capsys.readouterr().err.strip().splitlines()
    assert len(err) == 1, err
    return err[0]


def test_pull_and_push_refuse_a_node_without_canicals_objects(foreign: str, tmp_path: Path, capsys) -> None:
    bus = ["--interface", "virtual", "--channel", foreign, "--node", "8", "--timeout", "1"]
    assert main(["pull", *bus, "-o", str(tmp_path / "x.yaml")]) == 2
    line = one_line(capsys)
    assert "vendor 0x0000abcd" in line and "does not carry canical's coefficient objects" in line
    assert "canical serve" in line and not list(tmp_path.iterdir())
    sets = write_sets(tmp_path)
    assert main(["push", *bus, str(sets["x"])]) == 2
    assert "does not carry canical's coefficient objects" in one_line(capsys)


def test_serve_check_with_device_refuses_a_node_without_canicals_objects(foreign: str, tmp_path: Path,
                                                                       capsys) -> None:
    sets = write_sets(tmp_path, terms={"x": (), "y": (), "z": ()})
    config = tmp_path / "c.yaml"
    dbc = Path(__file__).parents[2] / "dbc" / "canical.dbc"
    config.write_text(yaml.safe_dump({
        "bus": {"interface": "virtual", "channel": foreign}, "dbc": str(dbc),
        "axes": {a: {"coefficients": str(p)} for a, p in sets.items()}, "device": {"node": 8}}))
    assert main(["serve", "--config", str(config), "--check"]) == 2
    assert "does not carry canical's coefficient objects" in one_line(capsys)


def test_export_dcf_asks_the_node_when_given_a_channel(foreign: str, tmp_path: Path, capsys) -> None:
    """Offline, export dcf says the node was not asked; with --channel a vendor's node is refused."""
    from support.imu_fixtures import imu_set

    from canical.sets import coefficient_file

    path = tmp_path / "imu-z.yaml"
    coefficient_file.save(path, imu_set("z"))
    out = tmp_path / "imu.dcf"
    assert main(["export", "dcf", str(path), "-o", str(out), "--node", "8", "--rated-range", "0"]) == 0
    assert "offline: node 0x08 was not asked" in capsys.readouterr().out
    out.unlink()
    assert main(["export", "dcf", str(path), "-o", str(out), "--node", "8", "--interface", "virtual",
                 "--channel", foreign, "--timeout", "1"]) == 2
    assert "does not carry canical's coefficient objects" in one_line(capsys)
    assert not out.exists()
