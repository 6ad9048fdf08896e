"""Executors: where a sweep's points run (``experiments.point_runs``: each as one process).
``LocalExecutor`` runs up to ``jobs`` side by side; ``experiments.ray_executor`` uses a Ray cluster.
"""

from __future__ import annotations

import subprocess
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from typing import Protocol

from coordinator.run_state import RunState
from experiments.point_runs import PointOutcome, PointTask, run_point
from experiments.slots import POINT_PRIORITY, Slots


class Executor(Protocol):
    name: str

    def run(self, tasks: list[PointTask], on_start: Callable[[PointTask], None],
            on_done: Callable[[PointTask, PointOutcome], None], cancel: threading.Event) -> None:
        """Run every task (unless cancelled), calling ``on_done`` once per finished task."""


# How long a cancelled point's run may take to stop its federates and write its records before
# it is killed (a run stops its federates in a few seconds; its records are kept either way).
CANCEL_GRACE_S = 60.0


class LocalExecutor:
    """Up to ``jobs`` points at once as processes on this host."""

    name = "local"

    def __init__(self, jobs: int = 1, slots: Slots | None = None) -> None:
        """``slots``: a pool shared with other work on this host (the coordinator's jobs), of
        which each point takes one while it runs."""
        if jobs < 1:
            raise ValueError(f"jobs must be >= 1, got {jobs}")
        self.jobs = jobs
        self.slots = slots

    def run(self, tasks: list[PointTask], on_start: Callable[[PointTask], None],
            on_done: Callable[[PointTask, PointOutcome], None], cancel: threading.Event) -> None:
        procs: dict[str, subprocess.Popen[bytes]] = {}
        stop = threading.Event()

        def one(task: PointTask) -> None:
            with self.slots.take(POINT_PRIORITY, cancel) if self.slots else nullcontext(True) as got:
                if not got or cancel.is_set():
                    return
                on_start(task)
                outcome = run_point(task, procs)
            # A point the cancel interrupted is no result (it may even have died before it could
            # say so): it stays unrecorded and runs again on resume.
            if not cancel.is_set() or outcome.status == RunState.COMPLETED:
                on_done(task, outcome)

        def forward_cancel() -> None:
            # Until the pool ends: a point that passed its check just before the cancel starts
            # its process after it, and is stopped too.
            stopped: dict[int, float] = {}  # pid -> when it was asked to stop
            while not stop.wait(0.2):
                if cancel.is_set():
                    for proc in list(procs.values()):
                        if proc.poll() is not None:
                            continue
                        asked = stopped.get(proc.pid)
                        if asked is None:
                            proc.terminate()  # the run cancels itself and stops its federates
                            stopped[proc.pid] = time.monotonic()
                        elif time.monotonic() - asked > CANCEL_GRACE_S:
                            proc.kill()  # hung while it stopped: the run's federates die with it

        watcher = threading.Thread(target=forward_cancel, daemon=True, name="sweep-cancel")
        watcher.start()
        try:
            with ThreadPoolExecutor(max_workers=self.jobs, thread_name_prefix="point") as pool:
                for f in [pool.submit(one, t) for t in tasks]:
                    f.result()
        finally:
            stop.set()
            watcher.join()


def make_executor(name: str, jobs: int | None, address: str | None = None) -> Executor:
    """``jobs``: points in flight at once (local default 1; Ray default: the cluster's CPUs)."""
    if name == "local":
        if address is not None:
            raise ValueError("--address is for the ray executor")
        return LocalExecutor(jobs or 1)
    if name == "ray":
        from experiments.ray_executor import RayExecutor
        return RayExecutor(address=address, jobs=jobs)
    raise ValueError(f"executor {name!r}: allowed are local, ray")
