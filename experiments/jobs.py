"""The coordinator's jobs: runs and sweeps behind one admission lock, in one store, served by one
pool of simulation slots sized to the host (docs/architecture.md sec. 12, "One job service").

Every job has a thread that waits for a slot per simulation, a waiting run before waiting sweep
points. At start, runs a dead coordinator left are salvaged and unfinished sweeps resumed.
"""

from __future__ import annotations

import json
import logging
import threading
from collections.abc import Callable
from pathlib import Path
from typing import Any

from coordinator.conductor import Progress
from coordinator.run import RunResult, execute_run, new_run_id, salvage_run
from coordinator.run_state import ACTIVE, ENDED, RunState
from experiments.executors import Executor, LocalExecutor
from experiments.job_store import JobKind, JobStore
from experiments.points import expand
from experiments.records import SweepDir
from experiments.report import load_sweep_spec
from experiments.slots import RUN_PRIORITY, Slots
from experiments.spec import SweepSpec
from experiments.sweep import Sweep
from scenario.schema import Scenario

log = logging.getLogger(__name__)

# The state of a point of a completed sweep that never ran: its series had stopped before its load.
PASSED_OVER = "passed_over"

# Why a run a previous coordinator left unfinished failed.
ORPHAN_REASON = "coordinator stopped during the run"


class TooMuchWork(Exception):
    """As many jobs are pending or running as the coordinator queues."""


class JobService:
    """Owns the store, the slots and the job threads.

    ``execute`` runs one run in this process (default ``execute_run``); ``make_executor(slots)``
    makes a sweep's executor (default: a local one whose points take slots). ``on_progress(run
    id, sim s, real-time factor)``, ``on_admitted(kind)``, ``on_ended(job_id, kind, state)`` and
    ``on_point_done(state)`` let the interface count what happens."""

    def __init__(self, db_path: Path, runs_root: Path, sweeps_root: Path, scenarios_dir: Path, *,
                 slots: int = 1, max_queued: int = 32, execute: Callable[..., RunResult] = execute_run,
                 make_executor: Callable[[Slots], Executor] | None = None) -> None:
        self.runs_root, self.sweeps_root, self.scenarios_dir = runs_root, sweeps_root, scenarios_dir
        self.max_queued = max_queued
        self.execute = execute
        self.slots = Slots(slots)
        self.make_executor = make_executor or (lambda s: LocalExecutor(s.size, slots=s))
        self.on_progress: Callable[[str, float, float], None] = lambda job_id, sim_s, rtf: None
        self.on_ended: Callable[[str, JobKind, str], None] = lambda job_id, kind, state: None
        self.on_admitted: Callable[[JobKind], None] = lambda kind: None
        self.on_point_done: Callable[[str], None] = lambda state: None
        self.store = JobStore(db_path)
        self._admit = threading.Lock()  # the room check and the admission, as one step
        self._cancels: dict[str, threading.Event] = {}
        self._threads: dict[str, threading.Thread] = {}
        self._sweeps: dict[str, Sweep] = {}  # running, for their progress
        self._points: dict[str, list[dict[str, Any]]] = {}
        self._closing = False  # the service stops: its sweeps stop here and resume at the next start
        self._user_cancelled: set[str] = set()  # jobs the user cancelled (they never resume)
        for run_id, results_dir in self.store.fail_active_runs(ORPHAN_REASON):
            try:  # what the run's federates streamed before the coordinator died is kept
                salvage_run(Path(results_dir), ORPHAN_REASON)
            except OSError as exc:
                log.warning("run %s: could not close its records in %s: %s", run_id, results_dir, exc)
        for row in self.store.list(JobKind.SWEEP, ACTIVE):  # left by a coordinator that stopped
            self._start(row["job_id"], self._sweep_job)

    def queued(self) -> int:
        """Runs and sweeps pending or running."""
        return len(self._cancels)

    def _check_room(self) -> None:
        n = self.queued()
        if n >= self.max_queued:
            raise TooMuchWork(f"{n} runs and sweeps are pending or running, the most this coordinator queues: "
                              f"max_queued (--max-queued, COSIM5G_MAX_QUEUED) = {self.max_queued}; "
                              "retry when one has ended")

    def submit_run(self, sc: Scenario) -> str:
        """Queue a run; its id. TooMuchWork when the queue is full."""
        with self._admit:
            self._check_room()
            run_id = new_run_id(sc)
            self.store.add(run_id, JobKind.RUN, sc.name, sc.model_dump(mode="json"), self.runs_root / run_id)
            self._start(run_id, lambda job_id, cancel: self._run_job(job_id, sc, cancel))
        self.on_admitted(JobKind.RUN)
        return run_id

    def submit_sweep(self, spec: SweepSpec) -> tuple[str, int]:
        """Queue a sweep: its id and number of points. TooMuchWork when the queue is full."""
        with self._admit:
            self._check_room()
            sweep = Sweep.create(spec, self.sweeps_root, scenarios_dir=self.scenarios_dir, allow_paths=False)
            sid = sweep.sweep_id
            self.store.add(sid, JobKind.SWEEP, spec.name, spec.model_dump(mode="json"), sweep.dir.path)
            self._start(sid, self._sweep_job)
        self.on_admitted(JobKind.SWEEP)
        return sid, len(self.points(sid))

    def cancel(self, job_id: str) -> bool:
        """Ask a pending or running job to stop; False if it has ended."""
        ev = self._cancels.get(job_id)
        if ev is None:
            return False
        self._user_cancelled.add(job_id)
        ev.set()
        return True

    def _start(self, job_id: str, work: Callable[[str, threading.Event], None]) -> None:
        cancel = self._cancels[job_id] = threading.Event()

        def job() -> None:
            try:
                work(job_id, cancel)
            finally:
                self._cancels.pop(job_id, None)
                self._threads.pop(job_id, None)

        thread = self._threads[job_id] = threading.Thread(target=job, daemon=True, name=f"job-{job_id}")
        thread.start()

    def _end(self, job_id: str, kind: JobKind, state: str, reason: str | None,
             kpis: dict[str, Any] | None = None) -> None:
        self.store.finish(job_id, state, reason, kpis)
        self.on_ended(job_id, kind, state)

    def _run_job(self, run_id: str, sc: Scenario, cancel: threading.Event) -> None:
        try:
            with self.slots.take(RUN_PRIORITY, cancel) as got:
                if not got:
                    self._end(run_id, JobKind.RUN, RunState.CANCELLED, "cancelled before it started")
                    return
                self.store.set_running(run_id)

                def progress(p: Progress) -> None:
                    rtf = (p.t_us / 1e6) / p.wall_s if p.wall_s > 0 else 0.0
                    self.store.set_progress(run_id, p.t_us / 1e6, rtf)
                    self.on_progress(run_id, p.t_us / 1e6, rtf)

                result = self.execute(sc, self.runs_root, on_progress=progress, cancel=cancel, run_id=run_id)
            self._end(run_id, JobKind.RUN, result.status, result.reason, result.kpis)
        except Exception as exc:  # a broken run must not take the coordinator with it
            self._end(run_id, JobKind.RUN, RunState.FAILED, f"coordinator error: {exc}")

    def _sweep_job(self, sid: str, cancel: threading.Event) -> None:
        row = self.store.get(sid, JobKind.SWEEP)
        if row is None:
            return
        try:
            sweep_dir = Path(row["dir"])
            sweep = Sweep(load_sweep_spec(sweep_dir), sweep_dir, self.scenarios_dir, allow_paths=False)
            self._sweeps[sid] = sweep
            self.store.set_running(sid)
            sweep.run(self.make_executor(self.slots), cancel, self._sweep_event)
            state = sweep.dir.meta().get("state", RunState.COMPLETED)
            if state == RunState.CANCELLED and self._closing and sid not in self._user_cancelled:
                return  # left running in the store: the next start resumes it
            self._end(sid, JobKind.SWEEP, state, "cancelled by the user" if state == RunState.CANCELLED else None)
        except Exception as exc:  # a broken sweep must not take the coordinator with it
            self._end(sid, JobKind.SWEEP, RunState.FAILED, f"coordinator error: {type(exc).__name__}: {exc}")
        finally:
            self._sweeps.pop(sid, None)

    def _sweep_event(self, kind: str, data: dict[str, Any]) -> None:
        if kind == "point_done":
            self.on_point_done(data["status"])

    def points(self, sweep_id: str) -> list[dict[str, Any]]:
        """Every point of the sweep's grid and base seeds: values, seed, key (cached)."""
        if sweep_id not in self._points:
            row = self.store.get(sweep_id, JobKind.SWEEP)
            if row is None:
                return []
            try:
                spec = SweepSpec.model_validate(row["request"])
                self._points[sweep_id] = [{"values": p.values, "seed": p.seed, "key": p.key}
                                          for p in expand(spec, self.scenarios_dir, allow_paths=False)]
            except (ValueError, OSError) as exc:
                # A sweep of before a scenario was renamed or a check tightened: its grid no
                # longer expands; it is described from its records.
                log.warning("sweep %s: its spec no longer expands (%s); described from its records",
                            sweep_id, exc)
                return []
        return self._points[sweep_id]

    def describe(self, sweep_id: str) -> dict[str, Any] | None:
        """A sweep's state, progress, per-point state and KPIs so far, capacity once done."""
        row = self.store.get(sweep_id, JobKind.SWEEP)
        if row is None:
            return None
        sweep_dir = Path(row["dir"])
        records = {r["key"]: r for r in SweepDir(sweep_dir).records()}
        sweep = self._sweeps.get(sweep_id)
        snap = sweep.progress.snapshot(self.slots.size) if sweep is not None else None
        in_flight = {c["point"]: c for c in (snap or {}).get("running", [])}
        points = []
        known = set()
        for p in self.points(sweep_id):
            known.add(p["key"])
            point = _point_state(p, records.get(p["key"]), in_flight)
            if row["state"] == RunState.COMPLETED and point["state"] == RunState.PENDING:
                # A completed sweep ran every point but those whose series had stopped
                # (``capacity.stop_after``).
                point["state"] = PASSED_OVER
            points.append(point)
        # Seeds added by repeat_until are not in the base grid: list them from the records.
        for key, rec in records.items():
            if key not in known:
                points.append(_point_state({"values": rec["values"], "seed": rec["seed"], "key": key}, rec, {}))
        cap_path = sweep_dir / "capacity.json"
        done = sum(1 for p in points if p["state"] in ENDED)
        passed_over = sum(1 for p in points if p["state"] == PASSED_OVER)
        return {
            "sweep_id": sweep_id, "name": row["name"], "state": row["state"], "reason": row["reason"],
            "created_s": row["created_s"], "started_s": row["started_s"], "finished_s": row["finished_s"],
            "spec": row["request"],
            "progress": {"points_total": max(len(points) - passed_over, snap["total"] if snap else 0),
                         "points_done": done, "points_passed_over": passed_over,
                         "points_failed": sum(1 for p in points if p["state"] in ENDED and p["state"] != RunState.COMPLETED),
                         "eta_s": snap["eta_s"] if snap else None},
            "points": points,
            "capacity": json.loads(cap_path.read_text()) if row["state"] not in ACTIVE and cap_path.is_file() else None,
        }

    def close(self) -> None:
        """Stop every job and wait for their threads (a minute at most): runs are cancelled,
        sweeps stop and are resumed by the next start."""
        self._closing = True
        for ev in list(self._cancels.values()):
            ev.set()
        for thread in list(self._threads.values()):
            thread.join(timeout=60)
        self.store.close()


def _point_state(p: dict[str, Any], rec: dict[str, Any] | None, in_flight: dict[str, Any]) -> dict[str, Any]:
    label = " ".join(f"{k}={v}" for k, v in p["values"].items()) + f" seed={p['seed']}"
    out: dict[str, Any] = {"values": p["values"], "seed": p["seed"], "key": p["key"]}
    if rec is not None:
        k = rec.get("kpis", {})
        out.update(state=rec["status"], reason=rec.get("reason"), run_id=rec["run_id"],
                   kpis={n: k.get(n) for n in ("tasks", "tasks_placed", "task_success_rate", "ul_injected_mbps",
                                               "ul_throughput_mbps", "ul_ip_latency_ms.p50",
                                               "ul_ip_latency_ms.p99", "real_time_factor")})
    elif label in in_flight:
        out.update(state=RunState.RUNNING, sim_time_s=in_flight[label]["sim_time_s"])
    else:
        out.update(state=RunState.PENDING)
    return out
