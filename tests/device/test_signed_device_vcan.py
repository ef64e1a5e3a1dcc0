"""Signed sets pushed to the emulated IMU as its own process on a real SocketCAN vcan, with the
commands a lab uses: ``canical provision``, ``canical push``, a power cut, ``canical pull --trust``.

The in-process tests (``test_signed_device.py``) try every refusal against the device's rules; this
one does the lab's round on a real bus: the key provisioned and closed, the refused kinds of set
each ended by the device with one line (exit 2) and the running set kept, the anti-rollback
counter surviving a power cut, a newer signed set adopted and pulled back verified, with the very
signature the lab made.
"""

from __future__ import annotations

from pathlib import Path

import pytest
from support.signed_sets import make_lab, refused_case, signed_copy
from test_imu_canopen_vcan import assert_one_line_error, bus_args, canical, client, device, ids, write_sets

from canical.frames.imu_dictionary import AXES
from canical.sets import coefficient_file
from canical.sets.coefficient_file import set_crc
from canical.sets.signed_file import read_set_file

pytestmark = pytest.mark.vcan

#: The cases the device itself refuses (a CRC that does not match is refused by the tool before
#: it writes anything; ``test_imu_canopen_vcan`` tries that), and the words of its one line. A
#: signature record relabelled for another sensor is no case here: the device checks the signature
#: against its own sensor id, which the lab did sign; a set signed for another sensor is below.
DEVICE_REFUSALS = {
    "unsigned": "not signed",
    "untrusted": "not",
    "tampered-crc-recomputed": "signature",
    "rollback": "older",
}


def _signed(folder: Path, family: int, lab, version: int, sensor: str | None = None
            ) -> tuple[list[Path], list[Path]]:
    unsigned = [Path(p) for p in write_sets(folder / "unsigned", family, sensor)]
    signed = [signed_copy(p, folder / p.name, lab.key, version) for p in unsigned]
    return unsigned, signed


def test_the_labs_round_on_a_real_bus(vcan_channel: str, tmp_path: Path) -> None:
    lab = make_lab(tmp_path / "keys")
    _, first = _signed(tmp_path / "v1", 0, lab, 1)
    unsigned, newer = _signed(tmp_path / "v2", 1, lab, 2)
    z = next(p for p in unsigned if p.name == "imu-z.yaml")
    (tmp_path / "bad").mkdir()
    with device(vcan_channel, tmp_path, "--rate", "50") as dev:
        provisioned = canical("provision", "--key", str(lab.pub), "--close", *bus_args(vcan_channel))
        assert provisioned.returncode == 0, provisioned.stderr
        pushed = canical("push", *map(str, first), *bus_args(vcan_channel))
        assert pushed.returncode == 0, pushed.stderr
        for case, words in DEVICE_REFUSALS.items():
            # rolled back: signed as version 0 while version 1 runs; the others as a newer version 2
            bad = refused_case(case, z, tmp_path / "bad", lab, version=1 if case == "rollback" else 2)
            refused = canical("push", str(bad), *bus_args(vcan_channel))
            assert_one_line_error(refused, words)
            with client(vcan_channel) as c:
                assert c.status().active_ids == ids(0), case
        _, elsewhere = _signed(tmp_path / "other", 1, lab, 3, sensor="IMU-OTHER")
        assert_one_line_error(canical("push", str(elsewhere[2]), *bus_args(vcan_channel)), "IMU-OTHER")
        dev.kill()  # power cut: the key, the closed provisioning and the counter must come back
        dev.start()
        rollback = refused_case("rollback", z, tmp_path / "bad", lab, version=1)
        assert_one_line_error(canical("push", str(rollback), *bus_args(vcan_channel)), "older")
        adopted = canical("push", *map(str, newer), *bus_args(vcan_channel))
        assert adopted.returncode == 0, adopted.stderr
        with client(vcan_channel) as c:
            assert c.status().active_ids == ids(1)
        out = str(tmp_path / "pulled-{axis}.yaml")
        pulled = canical("pull", *bus_args(vcan_channel), "--trust", str(lab.pub), "-o", out)
        assert pulled.returncode == 0, pulled.stderr
        stranger = canical("pull", *bus_args(vcan_channel), "--trust", str(lab.other_pub), "-o",
                           str(tmp_path / "stranger-{axis}.yaml"))
        assert_one_line_error(stranger, "not trusted")
    for axis in AXES:
        pulled_set = coefficient_file.load(tmp_path / f"pulled-{axis}.yaml")
        assert set_crc(pulled_set) == ids(1)[axis]
        signed = read_set_file(tmp_path / "v2" / f"imu-{axis}.yaml").signed.record
        assert read_set_file(tmp_path / f"pulled-{axis}.yaml").signed.record == signed
