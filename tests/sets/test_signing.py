"""Signed sets: a set signed by a trusted key is verified; every other set is refused in one line.

The cases are the issue's (unsigned, an untrusted key, one bit of a coefficient changed after
signing with and without the CRC recomputed, another sensor, a rollback, a truncated and a
garbage signature), on a single-axis set and on an IMU set, through the file readers and
through ``canical verify`` as a user runs it.
"""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from support.signed_sets import REFUSALS, make_lab, refused_case, signed_copy

from canical.commands.cli import main
from canical.errors import CanicalError
from canical.files.key_file import read_public, read_secret
from canical.sets import coefficient_file, imu_set
from canical.sets.signed_file import read_set_file, sign_file, verified
from canical.sets.signing import SignedContent, TrustedKey, key_id_of, new_seed, public_of, sign, verify

SETS = Path(__file__).parents[1] / "data" / "sets"
KINDS = {"single": SETS / "daemon-z.yaml", "imu": SETS / "imu-triad.yaml"}


@pytest.fixture(scope="module")
def lab(tmp_path_factory):
    return make_lab(tmp_path_factory.mktemp("keys"))


def trusted(lab) -> tuple[TrustedKey, ...]:
    return (TrustedKey(read_public(lab.pub), str(lab.pub)),)


@pytest.mark.parametrize("kind", sorted(KINDS))
def test_a_signed_set_keeps_its_crc_and_verifies(kind, lab, tmp_path):
    before = read_set_file(KINDS[kind])
    signed = signed_copy(KINDS[kind], tmp_path / "s.yaml", lab.key, version=3)
    after = read_set_file(signed)
    assert after.crc == before.crc  # the signature is outside the CRC's content
    assert after.signed.canonical == before.signed.canonical
    record = verified(after.signed, trusted(lab), 3, str(signed))
    assert (record.version, record.key_id) == (3, key_id_of(read_public(lab.pub)))
    loader = imu_set.load if kind == "imu" else coefficient_file.load
    assert loader(signed) == loader(KINDS[kind])  # an unsigned reader reads the same set


@pytest.mark.parametrize("kind", sorted(KINDS))
@pytest.mark.parametrize("case", sorted(REFUSALS))
def test_every_unsigned_or_wrongly_signed_set_is_refused_in_one_line(case, kind, lab, tmp_path, capsys):
    path = refused_case(case, KINDS[kind], tmp_path, lab, version=2)
    with pytest.raises(CanicalError) as refused:
        checked = read_set_file(path)
        verified(checked.signed, trusted(lab), 2, str(path))
    assert REFUSALS[case] in str(refused.value)
    if case != "rollback":  # verify has no running set: a lower version is still the lab's
        assert main(["verify", str(path), "--trust", str(lab.pub)]) == 2
        err = capsys.readouterr().err
        assert err.count("\n") == 1 and REFUSALS[case] in err


def test_sign_counts_versions_up_and_verify_says_so(lab, tmp_path, capsys):
    path = signed_copy(KINDS["single"], tmp_path / "s.yaml", lab.key, version=4)
    assert main(["sign", str(path), "--key", str(lab.key)]) == 0
    assert read_set_file(path).signed.record.version == 5
    assert main(["verify", str(path), "--trust", str(lab.other_pub), "--trust", str(lab.pub)]) == 0
    assert capsys.readouterr().out.splitlines()[-1].endswith("version 5, for sensor IMU-0001: trusted")


def test_keygen_writes_a_private_key_only_its_owner_reads(tmp_path, capsys):
    assert main(["keygen", str(tmp_path / "lab")]) == 0
    assert (tmp_path / "lab.key").stat().st_mode & 0o777 == 0o600
    assert main(["keygen", str(tmp_path / "lab")]) == 2  # never over an existing key
    (tmp_path / "lab.key").chmod(0o644)
    with pytest.raises(CanicalError, match="readable by others"):
        read_secret(tmp_path / "lab.key")


@pytest.mark.parametrize("bad", ["", "canical-ed25519-secret AAAA\n", "ssh-ed25519 AAAA x\n"])
def test_a_wrong_key_file_is_one_line(bad, lab, tmp_path, capsys):
    key = tmp_path / "bad.pub"
    key.write_text(bad)
    assert main(["verify", str(KINDS["single"]), "--trust", str(key)]) == 2
    assert capsys.readouterr().err.count("\n") == 1


def test_a_damaged_set_is_never_signed(lab, tmp_path):
    path = refused_case("tampered", KINDS["single"], tmp_path, lab)
    text = path.read_text()
    with pytest.raises(CanicalError, match="CRC mismatch"):
        sign_file(path, read_secret(lab.key), 9)
    assert path.read_text() == text


def test_the_command_line_bounds_versions_as_the_signer_does():
    from canical.commands import sign
    from canical.sets import signing

    assert sign.MAX_VERSION == signing.MAX_VERSION


def test_calibrate_signs_each_new_set_one_version_up(lab, tmp_path, capsys):
    from support.sessions import write_session

    from canical.sim.sessions import paper_session

    session = write_session(tmp_path / "session.csv", paper_session(seed=5))
    out = tmp_path / "imu-z.yaml"
    for version in (1, 2):
        assert main(["calibrate", str(session), "-o", str(out),
                     "--sign-key", str(lab.key)]) == 0
        assert capsys.readouterr().out.splitlines()[-1].endswith(f"version {version}, for sensor SIM-0001")
    checked = read_set_file(out)
    assert verified(checked.signed, trusted(lab), 2, str(out)).version == 2
    (tmp_path / "bad.key").write_text("nonsense\n")
    (tmp_path / "bad.key").chmod(0o600)
    assert main(["calibrate", str(session), "-o", str(tmp_path / "x.yaml"), "--sign-key",
                 str(tmp_path / "bad.key")]) == 2
    assert not (tmp_path / "x.yaml").exists()


@settings(max_examples=200, deadline=None)
@given(data=st.data())
def test_any_change_to_what_is_signed_or_to_the_signature_is_refused(data, lab_keys) -> None:
    """One bit of the content, of the signature, or another version or sensor: never verified."""
    seed, trusted_keys = lab_keys
    canonical = data.draw(st.binary(min_size=1, max_size=64), label="content")
    good = sign(seed, canonical, 7, "S1")
    verify(SignedContent(good, canonical, "S1"), trusted_keys, "set")  # the original passes
    where = data.draw(st.sampled_from(["content", "signature", "version", "sensor"]))
    if where == "content":
        bit = data.draw(st.integers(0, 8 * len(canonical) - 1))
        canonical = flip(canonical, bit)
        record = good
    elif where == "signature":
        record = replace(good, signature=flip(good.signature, data.draw(st.integers(0, 8 * 64 - 1))))
    elif where == "version":
        record = replace(good, version=data.draw(st.integers(0, 2**63 - 1).filter(lambda v: v != 7)))
    else:
        record = replace(good, sensor_id=data.draw(st.text(min_size=1).filter(lambda s: s != "S1")))
    with pytest.raises(CanicalError):
        verify(SignedContent(record, canonical, record.sensor_id), trusted_keys, "set")


def flip(data: bytes, bit: int) -> bytes:
    out = bytearray(data)
    out[bit // 8] ^= 1 << (bit % 8)
    return bytes(out)


@pytest.fixture(scope="module")
def lab_keys():
    seed = new_seed()
    return seed, (TrustedKey(public_of(seed), "lab.pub"),)
