"""A process's own peak resident memory, and a Dask worker plugin that samples it as tasks finish.

Why not ``getrusage(RUSAGE_SELF).ru_maxrss``: Linux carries the high-water mark across exec (the
old address space's peak goes into the new program's ``ru_maxrss``), so a process started by fork
and exec (a ``subprocess``, a Dask worker of a LocalCluster, which ``spawn``s) begins with the
resident size of the process that started it. ``bench_fleet.py`` reported each worker's peak that
way: workers started after the bench's own process had grown in its earlier parts reported that
process's size (594 MB), whatever they replayed. ``VmHWM`` in ``/proc/self/status`` is the peak of
the process's own address space, which begins at its exec.
"""

from __future__ import annotations

import resource
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from distributed.diagnostics.plugin import WorkerPlugin

NAME = "canical-peak-sampler"


def own_peak_mb() -> float:
    """This process's peak resident set since its exec (``VmHWM``; ``ru_maxrss`` without /proc)."""
    status = Path("/proc/self/status")
    if status.exists():
        for line in status.read_text().splitlines():
            if line.startswith("VmHWM:"):
                return int(line.split()[1]) / 1024
    return rusage_peak_mb()


def rusage_peak_mb() -> float:
    """``ru_maxrss``: on Linux at least the starting process's resident size at the fork."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024


@dataclass(frozen=True)
class Sample:
    """A worker's peaks once it had finished ``tasks`` tasks."""

    tasks: int
    own_mb: float
    rusage_mb: float


class PeakSampler(WorkerPlugin):
    """Registered on a cluster's workers: after each task a worker finishes, its peaks."""

    def __init__(self) -> None:
        self.samples: list[Sample] = []

    def transition(self, key: Any, start: Any, finish: Any, **kwargs: Any) -> None:
        if finish == "memory":
            self.samples.append(Sample(len(self.samples) + 1, own_peak_mb(), rusage_peak_mb()))


def samples(dask_worker: Any) -> list[Sample]:
    """Run on each worker (``client.run``): its samples, one per task finished."""
    plugin: PeakSampler = dask_worker.plugins[NAME]
    return plugin.samples
