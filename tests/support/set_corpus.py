"""Record the set files the corpus test reads (tests/sets/test_set_corpus.py).

Run from a checkout's root: ``PYTHONPATH=.:tests:docs/scripts python -m support.set_corpus
tests/data/sets``. The files in tests/data/sets were written by commit 7d57cf5, before the set
became typed records: the models of every kind, every term kind (the splines too), the docs'
example, the IMU sets, and the daemon's sets, whose terms leave keys out. Creation times are
pinned, so a re-run on the same machine gives the same bytes.
"""

from __future__ import annotations

import dataclasses
import sys
import tempfile
from pathlib import Path
from typing import Any

FIXED = "2026-01-01T00:00:00Z"


def record(out: Path) -> None:
    import set_schema  # docs/scripts

    from canical.sets import coefficient_file, imu_set
    from support.daemon_fixtures import ALL_TERMS as DAEMON_ALL
    from support.daemon_fixtures import write_sets
    from support.firmware_cases import ALL_TERMS, MODELS, imu_every_term_set, model_set, term_set
    from support.imu_fixtures import imu_triad_set

    def pin(cset: Any) -> Any:
        return dataclasses.replace(cset, created=FIXED)

    for name in MODELS:
        (out / f"model-{name}.yaml").write_text(coefficient_file.dumps(pin(model_set(name))))
    (out / "every-term.yaml").write_text(coefficient_file.dumps(pin(term_set(tuple(ALL_TERMS)))))
    (out / "docs-example.yaml").write_text(set_schema.example_text())
    for name, imu in (("imu-every-term", imu_every_term_set()), ("imu-triad", imu_triad_set())):
        imu = dataclasses.replace(imu, created=FIXED, axes=tuple(pin(a) for a in imu.axes))
        (out / f"{name}.yaml").write_text(imu_set.dumps(imu))
    for tag, terms in (("daemon", None), ("daemon-all-terms", DAEMON_ALL)):
        with tempfile.TemporaryDirectory() as d:
            for axis, p in write_sets(Path(d), terms=terms).items():
                cset = pin(coefficient_file.load(p))
                (out / f"{tag}-{axis}.yaml").write_text(coefficient_file.dumps(cset))


if __name__ == "__main__":
    record(Path(sys.argv[1]))
