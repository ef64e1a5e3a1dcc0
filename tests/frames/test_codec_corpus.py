"""The compiled codecs against cantools on every message of a corpus of real DBC files.

The randomised layouts of ``test_frame_compiler.py`` cover what the compiler was written for;
this covers what users bring: the DBCs cantools ships for its own tests (vehicles' and
vendors' files, extended ids, Motorola layouts, offsets, odd widths, CAN FD lengths). Every
message canical would use (not refused as broken) is either compiled, and then decodes
random payloads and encodes values at and beyond each signal's edges exactly as cantools
does, or falls back to cantools itself (multiplexed, float, no signals), which is equal by
construction.
"""

from __future__ import annotations

import random
from collections import Counter
from pathlib import Path

import cantools
import pytest
from support.dbc_corpus import corpus_files
from test_frame_compiler import encode_both, same

from canical.frames.compiler import CantoolsCodec, NotCompilable, compile_codec
from canical.frames.dbc_files import why_broken

PAYLOADS = 25
VALUE_SETS = 25


def edge_values(rng: random.Random, message) -> list:
    """Per signal: its raw range's ends, one beyond, a half step (rounding), or a value inside."""
    out = []
    for sig in message.signals:
        n = sig.length
        lo, hi = (-(1 << (n - 1)), (1 << (n - 1)) - 1) if sig.is_signed else (0, (1 << n) - 1)
        raw = rng.choice((lo, hi, lo - 1, hi + 1, 0, rng.randint(lo, hi)))
        scale, offset = sig.conversion.scale, sig.conversion.offset
        half = rng.random() < 0.3
        out.append((raw + (0.5 if half else 0)) * scale + offset)
    return out


def check_message(message, rng: random.Random) -> str:
    """'compiled' after comparing it with cantools, or why it falls back to cantools."""
    try:
        compiled = compile_codec(message)
    except NotCompilable as exc:
        return f"cantools ({exc})"
    reference = CantoolsCodec(message)
    for _ in range(PAYLOADS):
        payload = bytes(rng.getrandbits(8) for _ in range(message.length))
        want, got = reference.decode(payload), compiled.decode(payload)
        equal = all(same(g, w) for g, w in zip(got, want, strict=True))
        assert equal, (message.name, payload.hex(), got, want)
        encode_both(compiled, reference, list(want))
    for _ in range(VALUE_SETS):
        encode_both(compiled, reference, edge_values(rng, message))
    return "compiled"


@pytest.fixture(scope="module")
def corpus() -> list[Path]:
    files = corpus_files()
    assert len(files) >= 80, f"the DBC corpus has {len(files)} files; cantools ships about 90"
    return files


def test_every_message_of_the_corpus_codes_as_cantools(corpus: list[Path]) -> None:
    outcomes: Counter[str] = Counter()
    for path in corpus:
        try:
            db = cantools.database.load_file(str(path), database_format="dbc", strict=False)
        except Exception:  # a file cantools cannot load is not one a user can bring
            outcomes["file cantools cannot load"] += 1
            continue
        for message in db.messages:
            if why_broken(message) is not None:  # canical refuses to use it (one line)
                outcomes["broken: refused"] += 1
                continue
            rng = random.Random(f"{path.name}:{message.name}")
            outcomes[check_message(message, rng).split(" (")[0]] += 1
    assert outcomes["compiled"] >= 300, outcomes  # the corpus is exercised, not skipped
    print(dict(outcomes))
