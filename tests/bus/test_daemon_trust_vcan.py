"""``canical serve`` with ``trust: require`` as a separate process on a real SocketCAN vcan.

The in-process tests (``test_daemon_trust.py``) try every refusal at start, on a file change and on
SIGHUP; this one does it where a vehicle meets it: the daemon from the deployable configuration,
frames streaming through the kernel, an operator replacing a set file and sending SIGHUP. Every
way a set can fail to be the lab's is offered in turn while the stream runs: each is refused with
one log line, no frame is corrected by it (every frame matches the running set's rates), and a
newer set the lab signed is then adopted from the next frames on.
"""

from __future__ import annotations

import signal
import time
from pathlib import Path

import numpy as np
import pytest
from support.daemon_fixtures import (
    DBC,
    DaemonProcess,
    Recorder,
    decode_stream,
    expected_rates,
    imu_stream,
    send_paced,
    write_config,
    write_sets,
)
from support.signed_sets import REFUSALS, make_lab, refused_case, signed_copy

from canical.files.atomic_file import write_text_atomic
from canical.frames.codec import load_dbc

pytestmark = pytest.mark.vcan

RATE_HZ = 400.0  # raw frames per second, as test_daemon_vcan
HALF_LSB = 0.005 + 1e-9
PER_OFFER = 150  # raw frames streamed after each offered set


def _generation(tmp_path: Path, lab, variant: int, version: int) -> tuple[dict[str, Path], dict[str, Path]]:
    """A generation of sets, unsigned and signed by the lab as ``version``."""
    folder = tmp_path / f"g{variant}"
    folder.mkdir()
    unsigned = write_sets(folder, variant=variant)
    signed = {a: signed_copy(p, folder / f"signed-{p.name}", lab.key, version) for a, p in unsigned.items()}
    return unsigned, signed


def test_refused_sets_correct_no_frame_and_a_newer_signed_set_is_adopted(vcan_channel: str,
                                                                          tmp_path: Path) -> None:
    import can

    db = load_dbc(DBC)
    lab = make_lab(tmp_path / "keys")
    unsigned, running = _generation(tmp_path, lab, 0, version=1)
    _, newer = _generation(tmp_path, lab, 1, version=2)
    offers = tmp_path / "offers"
    offers.mkdir()
    refused = [refused_case(case, unsigned["x"], offers, lab, version=1) for case in REFUSALS]

    live = tmp_path / "live"
    live.mkdir()
    live_paths = {a: live / f"imu-{a}.yaml" for a in ("x", "y", "z")}
    for axis, path in live_paths.items():
        write_text_atomic(path, running[axis].read_text())
    config = write_config(live, vcan_channel, watch_period_s=60.0,
                          trust={"keys": [str(lab.pub)], "require": True})
    stream = imu_stream(PER_OFFER * (len(refused) + 2), seed=11)
    cuts = [stream.raw_index[PER_OFFER * k] for k in range(1, len(refused) + 2)]
    rec = Recorder(vcan_channel)
    daemon = DaemonProcess(config)
    try:
        with can.Bus(interface="socketcan", channel=vcan_channel) as tx:
            start = 0
            for k, offer in enumerate([*refused, newer["x"]]):
                send_paced(tx, stream.frames[start:cuts[k]], RATE_HZ)
                write_text_atomic(live_paths["x"], offer.read_text())
                daemon.signal(signal.SIGHUP)
                time.sleep(0.3)  # the reload is built beside the frames; let it land between offers
                start = cuts[k]
            send_paced(tx, stream.frames[start:], RATE_HZ)
        rate_id = db.get_message_by_name("CANICAL_RATE").frame_id
        out = rec.wait_count(rate_id, len(stream.raw_index), timeout=30)
    finally:
        code = daemon.stop()
        rec.close()
    assert code == 0
    log = daemon.log()
    assert len(out) == len(stream.raw_index), log

    refusals = [line for line in log.splitlines() if "keeping set" in line]
    assert len(refusals) == len(REFUSALS), log
    for words in REFUSALS.values():
        assert sum(words in line for line in refusals) == 1, (words, refusals)

    # Which set corrected each frame, told by the x axis (its terms have no state): the running set
    # until the newer signed one, never a refused one (each refused x set is the running set
    # changed, so a frame it corrected would match neither).
    rates = db.get_message_by_name("CANICAL_RATE")
    sent = np.array([rates.decode(bytes(m.data), decode_choices=False)["RateX"] for m in out])
    signals = decode_stream(stream)
    old = expected_rates(signals, running)["x"]
    new = expected_rates(signals, {**running, "x": newer["x"]})["x"]
    labels = []
    for i, value in enumerate(sent):
        fits = [g for g, rate in enumerate((old, new)) if abs(value - rate[i]) <= HALF_LSB]
        assert len(fits) == 1, (i, value, old[i], new[i], log)
        labels.append(fits[0])
    switch = labels.index(1)
    assert labels == [0] * switch + [1] * (len(labels) - switch), log
    assert switch >= PER_OFFER * len(refused), (switch, log)  # adopted only once it was offered
