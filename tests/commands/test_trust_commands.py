"""``apply`` and ``push`` with ``--trust``: a set no trusted key signed is refused in one line before
anything is read or sent; a signed set goes through as it does without ``--trust``."""

from __future__ import annotations

from pathlib import Path

import pytest
from support.imu_fixtures import imu_set
from support.signed_sets import make_lab, refused_case, signed_copy

from canical.commands.cli import main
from canical.sets import coefficient_file

SETS = Path(__file__).parents[1] / "data" / "sets"


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    return make_lab(tmp_path_factory.mktemp("keys"))


@pytest.mark.parametrize("case", ["unsigned", "untrusted", "tampered-crc-recomputed"])
def test_apply_with_trust_refuses_a_set_the_lab_did_not_sign(case, lab, tmp_path, capsys) -> None:
    path = refused_case(case, SETS / "daemon-z.yaml", tmp_path, lab)
    out = tmp_path / "out.csv"
    (tmp_path / "in.csv").write_text("time_s,raw\n0.0,100\n0.01,120\n")
    assert main(["apply", str(path), str(tmp_path / "in.csv"), "-o", str(out), "--trust", str(lab.pub)]) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "Traceback" not in err
    assert not out.exists()


def test_apply_with_trust_corrects_with_a_signed_set(lab, tmp_path, capsys) -> None:
    path = signed_copy(SETS / "daemon-z.yaml", tmp_path / "z.yaml", lab.key)
    (tmp_path / "in.csv").write_text("time_s,raw\n0.0,100\n0.01,120\n")
    out = tmp_path / "out.csv"
    assert main(["apply", str(path), str(tmp_path / "in.csv"), "-o", str(out), "--trust", str(lab.pub)]) == 0
    assert "trusted" in capsys.readouterr().out and out.exists()


def test_push_with_trust_refuses_before_opening_the_bus(lab, tmp_path, capsys) -> None:
    path = tmp_path / "z.yaml"
    coefficient_file.save(path, imu_set("z"))
    args = ["push", str(path), "--node", "0x10", "--interface", "socketcan", "--channel", "canical-none",
            "--dry-run", "--trust", str(lab.pub)]
    assert main(args) == 2
    err = capsys.readouterr().err
    assert err.count("\n") == 1 and "not signed" in err
    signed = signed_copy(path, tmp_path / "signed-z.yaml", lab.key)
    assert main([*args[:1], str(signed), *args[2:]]) == 0  # the offline dry run, as without --trust
    assert "trusted" in capsys.readouterr().out


def test_calibrate_signs_an_imu_set_that_verify_trusts(lab, tmp_path, capsys) -> None:
    from support.triad import write_triad_sessions

    sessions = write_triad_sessions(tmp_path, seed=2)
    out = tmp_path / "imu.yaml"
    assert main(["calibrate", *map(str, sessions), "-o", str(out), "--sign-key", str(lab.key)]) == 0
    assert capsys.readouterr().out.splitlines()[-1].endswith("version 1, for sensor " +
                                                            imu_set_sensor(out))
    assert main(["verify", str(out), "--trust", str(lab.pub)]) == 0
    assert main(["verify", str(out), "--trust", str(lab.other_pub)]) == 2


def imu_set_sensor(path: Path) -> str:
    from canical.sets import imu_set

    return imu_set.load(path).sensor_id
