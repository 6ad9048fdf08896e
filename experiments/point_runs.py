"""Running one sweep point as a ``cosim5g run`` process that dies with the sweep: a crashing run
cannot take the sweep along, and its memory is returned when it ends."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from coordinator.run_state import RunState
from experiments.points import Point
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
    """A finished run's state, reason and KPIs; a run process that wrote no KPIs failed. Exit
    code 2 is a run refused before it started (bad input, or a run directory that exists): the
    KPIs there, if any, are not its own."""
    kpis_path = run_dir / "kpis.json"
    if code != 2 and kpis_path.is_file():
        kpis = json.loads(kpis_path.read_text())
        return kpis.get("status", RunState.FAILED), kpis.get("reason"), kpis
    tail = log_path.read_text(errors="replace").strip().splitlines()[-5:] if log_path.exists() else []
    reason = f"run process exited with code {code} and wrote no KPIs" + (": " + " | ".join(tail) if tail else "")
    return RunState.FAILED, reason, {}
