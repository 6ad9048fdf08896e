"""Executors: how a sweep's points are run. Every point is one ``cosim5g run`` process.

A point runs as its own process (isolation: a crashing run cannot take the sweep with it, and its
memory is returned when it ends) that dies with the sweep (a parent-death signal), so a killed
sweep leaves no run behind. ``LocalExecutor`` runs up to ``jobs`` points side by side on this
host; ``experiments.ray_executor.RayExecutor`` spreads them over a Ray cluster.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from contextlib import nullcontext
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Protocol

from coordinator.run_state import RunState
from experiments.points import Point
from experiments.slots import POINT_PRIORITY, Slots
from services.main import set_parent_death_signal


@dataclass
class PointTask:
    """A point ready to run: its config file, and where its run directory and log go."""

    point: Point
    config_path: Path
    run_id: str
    runs_dir: Path
    progress_file: Path | None = None
    log_file: Path | None = None


@dataclass
class PointOutcome:
    key: str
    run_id: str
    status: str  # a run's end state, or `failed` when the run process itself failed
    reason: str | None
    run_dir: Path
    wall_s: float
    kpis: dict[str, Any] = field(default_factory=dict)


class Executor(Protocol):
    name: str

    def run(self, tasks: list[PointTask], on_start: Callable[[PointTask], None],
            on_done: Callable[[PointTask, PointOutcome], None], cancel: threading.Event) -> None:
        """Run every task (unless cancelled), calling ``on_done`` once per finished task."""


def _die_with_parent() -> None:
    """In the child before exec: SIGTERM when the sweep process dies (Linux), which the run turns
    into a clean cancel."""
    set_parent_death_signal(signal.SIGTERM)


def run_command(config_path: Path, runs_dir: Path, run_id: str, progress_file: Path | None = None) -> list[str]:
    cmd = [sys.executable, "-m", "interfaces.cli", "run", str(config_path), "--quiet",
           "--results", str(runs_dir), "--run-id", run_id]
    if progress_file is not None:
        cmd += ["--progress-file", str(progress_file)]
    return cmd


def run_process(config_path: Path, runs_dir: Path, run_id: str, log_path: Path,
                progress_file: Path | None = None,
                procs: dict[str, subprocess.Popen[bytes]] | None = None) -> tuple[str, str | None, dict[str, Any]]:
    """Run one scenario file to its end as a ``cosim5g run`` process: (state, reason, KPIs).
    Never raises for a failing run."""
    env = {**os.environ, "MUJOCO_GL": os.environ.get("MUJOCO_GL", "egl")}
    log_path.parent.mkdir(parents=True, exist_ok=True)
    with open(log_path, "ab") as log:
        proc = subprocess.Popen(run_command(config_path, runs_dir, run_id, progress_file), stdout=log,
                                stderr=subprocess.STDOUT, env=env, stdin=subprocess.DEVNULL,
                                preexec_fn=_die_with_parent)
        if procs is not None:
            procs[run_id] = proc
        code = proc.wait()
        if procs is not None:
            procs.pop(run_id, None)
    return read_outcome(runs_dir / run_id, code, log_path)


def run_point(task: PointTask, procs: dict[str, subprocess.Popen[bytes]] | None = None) -> PointOutcome:
    """Run one point on this host."""
    t0 = time.monotonic()
    log_path = task.log_file or (task.runs_dir / f"{task.run_id}.log")
    status, reason, kpis = run_process(task.config_path, task.runs_dir, task.run_id, log_path,
                                       task.progress_file, procs)
    return PointOutcome(task.point.key, task.run_id, status, reason, task.runs_dir / task.run_id,
                        time.monotonic() - t0, kpis)


def read_outcome(run_dir: Path, code: int, log_path: Path) -> tuple[str, str | None, dict[str, Any]]:
    """A finished run's state, reason and KPIs; a run process that wrote no KPIs failed."""
    kpis_path = run_dir / "kpis.json"
    if kpis_path.is_file():
        kpis = json.loads(kpis_path.read_text())
        return kpis.get("status", RunState.FAILED), kpis.get("reason"), kpis
    tail = log_path.read_text(errors="replace").strip().splitlines()[-5:] if log_path.exists() else []
    reason = f"run process exited with code {code} and wrote no KPIs" + (": " + " | ".join(tail) if tail else "")
    return RunState.FAILED, reason, {}


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
            while not stop.wait(0.2):
                if cancel.is_set():
                    for proc in list(procs.values()):
                        if proc.poll() is None:
                            proc.terminate()  # the run cancels itself and stops its federates
                    return

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
