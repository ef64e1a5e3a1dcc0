"""Kill one worker process of a Dask cluster while it runs a command, once some tasks are done.

Why one helper: the fleet's commands promise that a worker lost mid-run changes nothing (the
scheduler runs its tasks again elsewhere); ``fleet analyse`` and ``fleet replay`` are both tested
that way, and the watcher thread, its events and its scheduler query are the same for both.
"""

from __future__ import annotations

import contextlib
import os
import signal
import threading
import time
from collections.abc import Iterator


def _tasks_done(dask_scheduler) -> int:  # type: ignore[no-untyped-def,unused-ignore]
    """Tasks whose result is held (run on the scheduler)."""
    return sum(ts.state == "memory" for ts in dask_scheduler.tasks.values())


@contextlib.contextmanager
def worker_killed_after(address: str, tasks_done: int) -> Iterator[list[int]]:
    """While the block runs, SIGKILL one worker of the cluster at ``address`` as soon as
    ``tasks_done`` tasks are done; yields a list that then holds how many were done at the kill
    (empty: the block ended first)."""
    import distributed

    killed: list[int] = []
    watching, finished_run = threading.Event(), threading.Event()

    def kill_one() -> None:
        with distributed.Client(address) as watcher:
            pid = next(iter(watcher.run(os.getpid).values()))
            watching.set()
            while not finished_run.is_set():
                finished = watcher.run_on_scheduler(_tasks_done)
                if finished >= tasks_done:
                    os.kill(pid, signal.SIGKILL)
                    killed.append(finished)
                    return
                time.sleep(0.002)

    thread = threading.Thread(target=kill_one)
    thread.start()
    try:
        assert watching.wait(30), "the watcher did not reach the cluster"
        yield killed
    finally:
        finished_run.set()
        thread.join()
