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

from canical.errors import CanicalError
from canical.fleet import dataset
from canical.fleet.analysis import PowerOnSums, summarise
from canical.progress import Progress

#: Vehicles per task: enough to amortise a task's overhead, few enough to spread over workers.
BATCH = 16


def summarise_folders(folders: Sequence[str]) -> PowerOnSums:
    """One task: a batch of vehicle folders' rows as per-power-on sums."""
    return PowerOnSums.concat([summarise(dataset.read_vehicle(Path(f))) for f in folders])


def batches(target: Path, size: int = BATCH) -> list[list[str]]:
    folders = [str(p) for p in dataset.vehicle_folders(target)]
    return [folders[i:i + size] for i in range(0, len(folders), size)]


def run(target: Path, scheduler: str | None, note: Callable[[str], None]) -> PowerOnSums:
    """Every vehicle's sums, on the embedded engine (``scheduler`` None) or on the cluster."""
    work = batches(target)
    if not work:
        raise CanicalError(f"{target}: no vehicle folders (vehicle=...): not a dataset fleet ingest wrote")
    if scheduler is None:
        progress = Progress("fleet analyse", len(work), unit="batches")
        parts = []
        for done, batch in enumerate(work, 1):
            parts.append(summarise_folders(batch))
            progress.update(done)
        return PowerOnSums.concat(parts)
    return PowerOnSums.concat(_on_cluster(scheduler, work, note))


def _on_cluster(scheduler: str, work: list[list[str]], note: Callable[[str], None]) -> list[PowerOnSums]:
    """The batches as tasks on a Dask distributed cluster; results in the batches' order."""
    try:
        from distributed import Client
    except ImportError:
        raise CanicalError("--scheduler needs dask's distributed package (pip install 'dask[distributed]')") \
            from None
    try:
        client = Client(scheduler, timeout=10)  # type: ignore[no-untyped-call]
    except (OSError, TimeoutError, ValueError) as exc:
        raise CanicalError(f"--scheduler {scheduler}: cannot connect ({exc})") from None
    with client:
        workers = len(client.scheduler_info().get("workers", {}))
        note(f"fleet analyse: {len(work)} batches on {scheduler} ({workers} workers)")
        futures = client.map(summarise_folders, work, pure=False)
        return list(client.gather(futures))  # type: ignore[no-untyped-call]
