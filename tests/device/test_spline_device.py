"""Spline terms on the device: in the bank payload, over SDO (``canical push``/``pull``), in a DCF,
run by the emulated IMU in the firmware's C evaluator; and the sets a device cannot hold (more
spline terms than its evaluator's slots, a knot beyond float32, content beyond its banks)
refused in one line before anything is written."""

from __future__ import annotations

import contextlib
import logging
import subprocess
import sys
import uuid
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import canopen
import numpy as np
import pytest
from support.firmware_cases import ALL_TERMS
from support.imu_fixtures import SERIAL, imu_set

from canical.commands.cli import main
from canical.device.bank_payload import decode_set, encode_set
from canical.device.emulated_imu import EmulatedImu, EmulatorConfig
from canical.device.sdo_download import plan_push
from canical.errors import CanicalError
from canical.frames.imu_dictionary import AXES, imu_objects
from canical.sets import coefficient_file
from canical.sets.admission import MAX_SPLINE_TERMS, MAX_TERMS, DeviceLimits, admission_problem
from canical.sets.coefficient_file import set_crc
from canical.sets.coefficients import CoefficientSet
from canical.sets.term_kinds import MAX_SPLINE_KNOTS
from canical.sets.terms import term_from_dict

NODE = 0x10
CAPACITY = 16384  # the EDS's "Coefficient bank capacity"
LIMITS = DeviceLimits(SERIAL, dict.fromkeys(AXES, 50.0), CAPACITY)


def with_terms(cset: CoefficientSet, terms: list[dict]) -> CoefficientSet:
    out = replace(cset, terms=tuple(term_from_dict(t) for t in terms))
    return coefficient_file.loads(coefficient_file.dumps(out))


def spline_set(axis: str, family: int = 0) -> CoefficientSet:
    """The axis's set with a spline of temperature in bias and in scale form, and one of its lag and
    of its rate of change (the lag's state on the device, then the spline): four spline terms."""
    return with_terms(imu_set(axis, family), [ALL_TERMS["channel-spline"], ALL_TERMS["channel-spline-scale"],
                                              ALL_TERMS["channel-lag-spline"],
                                              ALL_TERMS["channel-derivative-spline"]])


def wide_spline(rng: np.random.Generator, knots: int = MAX_SPLINE_KNOTS) -> dict:
    """A spline with the most knots, its numbers written with all 17 digits (a few kB of JSON)."""
    k = np.sort(rng.uniform(0.0, 50.0, knots))
    return dict(ALL_TERMS["channel-spline"], knots=k.tolist(),
                pieces=(rng.normal(0.0, 1.0, (knots - 1, 4)) * 1e-3).tolist())


def test_bank_payload_round_trip_of_a_spline_set() -> None:
    cset = spline_set("z")
    content, crc = encode_set(cset)
    assert b'"knots":[' in content and b'"pieces":[[' in content
    back = decode_set(content, crc, "bank Z A")
    assert back == cset and set_crc(back) == crc
    assert back.terms == cset.terms and any(t.spec.needs_spline for t in back.terms)
    assert admission_problem(cset, "z", LIMITS) is None


def test_sets_the_device_cannot_hold_are_refused_before_writing() -> None:
    rng = np.random.default_rng(5)
    base = imu_set("z")
    active, ids = dict.fromkeys(AXES), dict.fromkeys(AXES, 0)
    too_many = with_terms(base, [dict(ALL_TERMS["channel-spline"], coefficient=0.1 * (i + 1))
                                 for i in range(MAX_SPLINE_TERMS + 1)])
    spline = ALL_TERMS["channel-spline"]
    beyond_float = with_terms(base, [dict(spline, pieces=[[1e39, 0.0, 0.0, 0.0], *spline["pieces"][1:]])])
    too_long = with_terms(base, [wide_spline(rng) for _ in range(MAX_SPLINE_TERMS)])
    too_many_terms = with_terms(base, [ALL_TERMS["channel-offset"]] * (MAX_TERMS + 1))
    assert len(encode_set(too_long)[0]) > CAPACITY
    fits = with_terms(base, [wide_spline(rng)])
    assert len(encode_set(fits)[0]) <= CAPACITY
    plan_push({"z": ("fits.yaml", fits)}, LIMITS, active, ids, NODE)  # the most knots, one spline: pushed
    for cset, reason in [(too_many, f"{MAX_SPLINE_TERMS + 1} spline terms, the device's evaluator holds "
                                    f"{MAX_SPLINE_TERMS}"),
                         (beyond_float, "terms[0]: a spline knot, knot spacing or piece beyond float32"),
                         (too_many_terms, f"{MAX_TERMS + 1} terms, the device's evaluator holds {MAX_TERMS}"),
                         (too_long, f"the device's coefficient banks hold {CAPACITY}")]:
        with pytest.raises(CanicalError) as refused:
            plan_push({"z": ("z.yaml", cset)}, LIMITS, active, ids, NODE)
        message = str(refused.value)
        assert "\n" not in message and message.startswith("z.yaml: not for this device") and reason in message
    # without a stated capacity (the device's own bank check) only what its evaluator holds counts
    assert admission_problem(too_long, "z", DeviceLimits(SERIAL, LIMITS.rated_range_dps)) is None


@contextlib.contextmanager
def emulated(tmp_path: Path) -> Iterator[tuple[EmulatedImu, str]]:
    """The emulated IMU in this process, on a python-can virtual bus."""
    channel = f"spline-{uuid.uuid4().hex}"
    net = canopen.Network()
    net.connect(interface="virtual", channel=channel, receive_own_messages=False)
    try:
        config = EmulatorConfig(node_id=NODE, serial=SERIAL, state_path=tmp_path / "imu.json")
        yield EmulatedImu(config, net), channel
    finally:
        net.disconnect()


def bus(channel: str) -> list[str]:
    return ["--node", hex(NODE), "--interface", "virtual", "--channel", channel, "--timeout", "2"]


def test_push_pull_and_the_device_runs_a_spline_set_in_c(tmp_path: Path, capsys, caplog) -> None:
    sets = {a: spline_set(a) for a in AXES}
    paths = []
    for axis, cset in sets.items():
        paths.append(str(tmp_path / f"imu-{axis}.yaml"))
        coefficient_file.save(paths[-1], cset)
    big = tmp_path / "big.yaml"
    coefficient_file.save(big, with_terms(imu_set("z"), [wide_spline(np.random.default_rng(s))
                                                          for s in range(MAX_SPLINE_TERMS)]))
    with emulated(tmp_path) as (dev, channel):
        assert main(["push", str(big), *bus(channel)]) == 2
        err = capsys.readouterr().err.strip().splitlines()
        assert len(err) == 1 and f"the device's coefficient banks hold {CAPACITY}" in err[0], err
        nothing = dev.store.banks[("z", "A")].content == b"" and dev.store.lock_token == 0
        assert dev.store.activation_count == 0 and nothing  # not even the download lock taken
        assert main(["push", *paths, *bus(channel)]) == 0
        assert dev.store.activation_count == 1
        assert main(["pull", *bus(channel), "-o", str(tmp_path / "back-{axis}.yaml")]) == 0
        for axis, cset in sets.items():
            assert coefficient_file.load(tmp_path / f"back-{axis}.yaml") == cset
        with caplog.at_level(logging.INFO, logger="canical.imu"):
            correctors = dev.device_correctors()
        assert all(type(c).__name__ == "FirmwareCorrector" for c in correctors.values()), caplog.text
        assert caplog.text.count("corrected on the device with the firmware evaluator (C)") == 3


def test_dcf_export_carries_a_spline_set_and_refuses_one_too_long(tmp_path: Path) -> None:
    cset = spline_set("z")
    path = tmp_path / "z.yaml"
    coefficient_file.save(path, cset)
    out = tmp_path / "z.dcf"
    done = subprocess.run([sys.executable, "-m", "canical", "export", "dcf", str(path), "-o", str(out)],
                          capture_output=True, text=True, check=False)
    assert done.returncode == 0, done.stderr
    ref = imu_objects().bank("z", "A")
    value = canopen.import_od(str(out), NODE)[ref.index][ref.content].value
    assert decode_set(value, set_crc(cset), "dcf") == cset
    big = tmp_path / "big.yaml"
    coefficient_file.save(big, with_terms(imu_set("z"), [wide_spline(np.random.default_rng(s))
                                                          for s in range(MAX_SPLINE_TERMS)]))
    refused = subprocess.run([sys.executable, "-m", "canical", "export", "dcf", str(big), "-o",
                              str(tmp_path / "big.dcf")], capture_output=True, text=True, check=False)
    lines = refused.stderr.strip().splitlines()
    assert refused.returncode == 2 and len(lines) == 1, refused.stderr
    assert f"banks hold {CAPACITY}" in lines[0]
    assert not (tmp_path / "big.dcf").exists()
