"""``bench_fleet.py``'s peak memory per worker is the worker's own (``support/worker_peak.py``).

Why: the recorded 100 M-row replay printed 594 MB per worker against 240 MB at 10 M rows, read
as a worker's memory growing with the drives it replayed. It was ``ru_maxrss``, which a process
started by fork and exec inherits on Linux from the process that started it: there, the bench's
own, grown by its earlier parts. A worker started beside a process holding a large block must
report its own peak, well below that block, and one sample per task it finished.
"""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest
from support import worker_peak

BALLAST_MB = 300


@pytest.mark.skipif(not Path("/proc/self/status").exists(), reason="VmHWM is Linux's")
def test_a_worker_reports_its_own_peak_not_its_starters() -> None:
    distributed = pytest.importorskip("distributed")
    ballast = np.ones(BALLAST_MB * (1 << 20) // 8)  # written, so resident here
    with distributed.LocalCluster(n_workers=1, threads_per_worker=1, processes=True, host="127.0.0.1",
                                  dashboard_address=None) as cluster, distributed.Client(cluster) as client:
        client.register_plugin(worker_peak.PeakSampler(), name=worker_peak.NAME)
        assert client.gather(client.map(sum, [[1, 2]] * 3, pure=False)) == [3, 3, 3]
        (samples,) = client.run(worker_peak.samples).values()
    assert ballast.sum() > 0
    assert [s.tasks for s in samples] == [1, 2, 3]
    assert all(s.rusage_mb >= BALLAST_MB for s in samples)  # the trap: the starter's size
    assert all(s.own_mb < BALLAST_MB / 2 for s in samples)  # a fresh worker: about 60 MB
