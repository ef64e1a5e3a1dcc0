"""Where the per-vehicle work runs: in this process (the default, no cluster), or on a Dask
distributed cluster (``--scheduler tcp://HOST:PORT``), with the same result either way.

Why the same result: each task is a batch of vehicle folders reduced to per-power-on sums by the
same function (:func:`canical.fleet.analysis.summarise`), and the sums are combined in this
process in one fixed order (:meth:`~canical.fleet.analysis.PowerOnSums.concat`), whatever worker
ran which batch and in what order they finished. The workers read the dataset's files
themselves: the dataset must be at the same path for them (a shared or the same filesystem).
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from pathlib import Path
from typing import TypeVar

from canical.errors import CanicalError
from canical.fleet import dataset
from canical.fleet.analysis import PowerOnSums, summarise
from canical.progress import Progress

T = TypeVar("T")
R = TypeVar("R")
#: Vehicles per task: enough to amortise a task's overhead, few enough to spread over workers.
BATCH = 16


def summarise_folders(folders: Sequence[str]) -> PowerOnSums:
    """One task: a batch of vehicle folders' rows as per-power-on sums."""
    return PowerOnSums.concat([summarise(dataset.read_vehicle(Path(f))) for f in folders])


def batches(target: Path, size: int | None = None) -> list[list[str]]:
    """The dataset's vehicle folders in tasks of ``size`` (:data:`BATCH`, read when called: a default
    bound at definition kept a test's one vehicle per task from ever taking effect)."""
    size = size or BATCH
    folders = [str(p) for p in dataset.vehicle_folders(target)]
    return [folders[i:i + size] for i in range(0, len(folders), size)]


def run(target: Path, scheduler: str | None, note: Callable[[str], None]) -> PowerOnSums:
    """Every vehicle's sums, on the embedded engine (``scheduler`` None) or on the cluster."""
    work = batches(target)
    if not work:
        raise CanicalError(f"{target}: no vehicle folders (vehicle=...): not a dataset fleet ingest wrote")
    return PowerOnSums.concat(run_tasks(summarise_folders, work, scheduler, note, "fleet analyse", "batches"))


def run_tasks(fn: Callable[[T], R], work: Sequence[T], scheduler: str | None, note: Callable[[str], None],
              label: str, unit: str) -> list[R]:
    """``fn`` of each item, in the items' order: here one after the other (``scheduler`` None), or
    as tasks on a Dask distributed cluster (a lost worker's tasks run again elsewhere); a
    progress line as they finish either way."""
    progress = Progress(label, len(work), unit=unit)
    if scheduler is None:
        parts = []
        for done, item in enumerate(work, 1):
            parts.append(fn(item))
            progress.update(done)
        return parts
    return _on_cluster(fn, scheduler, work, note, label, progress)


def _on_cluster(fn: Callable[[T], R], scheduler: str, work: Sequence[T], note: Callable[[str], None],
                label: str, progress: Progress) -> list[R]:
    """The items as tasks on a Dask distributed cluster; results in the items' order."""
    try:
        from distributed import Client, as_completed
    except ImportError:
        raise CanicalError("--scheduler needs dask's distributed package (pip install 'dask[distributed]')") \
            from None
    try:
        client = Client(scheduler, timeout=10)  # type: ignore[no-untyped-call]
    except (OSError, TimeoutError, ValueError) as exc:
        raise CanicalError(f"--scheduler {scheduler}: cannot connect ({exc})") from None
    with client:
        workers = len(client.scheduler_info().get("workers", {}))
        note(f"{label}: {len(work)} tasks on {scheduler} ({workers} workers)")
        futures = client.map(fn, list(work), pure=False)
        for done, _ in enumerate(as_completed(futures), 1):  # type: ignore[no-untyped-call]
            progress.update(done)
        return list(client.gather(futures))  # type: ignore[no-untyped-call]
