"""The sweep engine: expand a spec into points, run those not yet completed, record each as it
ends, add seeds where a grid point has too few tasks, and rebuild the report.

One engine for every caller (CLI, REST API, policy evaluation). A sweep directory is its own
state: running the engine on it again (``--resume``) reruns only the points not completed.
"""

from __future__ import annotations

import contextlib
import itertools
import json
import math
import secrets
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from coordinator.run_state import RunState
from experiments.executors import Executor
from experiments.point_runs import PointOutcome, PointTask
from experiments.points import Point, expand, make_point, write_point_config
from experiments.records import SweepDir, flatten_kpis
from experiments.report import rebuild
from experiments.spec import SCENARIOS_DIR, SweepSpec, base_path, dump_spec
from scenario.schema import SEED_LIMIT

DEFAULT_ROOT = Path("results") / "sweeps"


def new_sweep_id(spec: SweepSpec) -> str:
    stamp = datetime.now(UTC).strftime("%Y%m%d-%H%M%S")
    return f"{spec.name}-{stamp}-{secrets.token_hex(3)}"


@dataclass
class InFlight:
    label: str
    progress_file: Path | None
    started: float


@dataclass
class SweepProgress:
    """What a progress bar or the REST API shows while a sweep runs."""

    total: int = 0
    done: int = 0
    failed: int = 0
    skipped: int = 0  # completed by an earlier invocation (resume)
    passed_over: int = 0  # not run: their series had stopped (capacity.stop_after)
    wall0: float = field(default_factory=time.monotonic)
    point_wall: list[float] = field(default_factory=list)
    in_flight: dict[str, InFlight] = field(default_factory=dict)
    lock: threading.Lock = field(default_factory=threading.Lock)

    def snapshot(self, jobs: int = 1) -> dict[str, Any]:
        with self.lock:
            current: list[dict[str, Any]] = []
            for run_id, f in self.in_flight.items():
                sim = end = None
                if f.progress_file is not None and f.progress_file.is_file():
                    try:
                        p = json.loads(f.progress_file.read_text())
                        sim, end = p["sim_time_s"], p["end_s"]
                    except (json.JSONDecodeError, KeyError, OSError):
                        pass
                current.append({"run_id": run_id, "point": f.label, "sim_time_s": sim, "end_s": end,
                                "wall_s": time.monotonic() - f.started})
            remaining = self.total - self.done - self.skipped
            eta = None
            if self.point_wall:
                mean = sum(self.point_wall) / len(self.point_wall)
                in_progress = sum(min(c["wall_s"], mean) for c in current)
                eta = max(0.0, (remaining * mean - in_progress) / max(1, jobs))
            return {"total": self.total, "done": self.done + self.skipped, "failed": self.failed,
                    "passed_over": self.passed_over,
                    "running": current, "eta_s": eta, "wall_s": time.monotonic() - self.wall0}


class Sweep:
    """One sweep directory and the engine that fills it."""

    def __init__(self, spec: SweepSpec, sweep_dir: Path, scenarios_dir: Path = SCENARIOS_DIR,
                 allow_paths: bool = True) -> None:
        self.spec = spec
        self.dir = SweepDir(sweep_dir)
        self.scenarios_dir = scenarios_dir
        self.allow_paths = allow_paths
        self.progress = SweepProgress()

    @classmethod
    def create(cls, spec: SweepSpec, root: Path = DEFAULT_ROOT, sweep_id: str | None = None,
               scenarios_dir: Path = SCENARIOS_DIR, allow_paths: bool = True) -> Sweep:
        sweep_id = sweep_id or new_sweep_id(spec)
        sweep = cls(spec, root / sweep_id, scenarios_dir, allow_paths)
        sweep.dir.create({"sweep_id": sweep_id, "name": spec.name, "state": RunState.PENDING,
                          "created": datetime.now(UTC).isoformat(timespec="seconds")}, dump_spec(spec))
        return sweep

    @property
    def sweep_id(self) -> str:
        return str(self.dir.meta().get("sweep_id", self.dir.path.name))

    def _task(self, point: Point) -> PointTask:
        prefix = point.key[:12]
        attempt = sum(1 for _ in self.dir.runs.glob(f"{prefix}-*/")) + 1
        run_id = f"{prefix}-{attempt}"
        return PointTask(point=point, config_path=write_point_config(point, self.dir.configs), run_id=run_id,
                         runs_dir=self.dir.runs, progress_file=self.dir.progress / f"{run_id}.json",
                         log_file=self.dir.path / "logs" / f"{run_id}.log")

    def _record(self, task: PointTask, outcome: PointOutcome) -> dict[str, Any]:
        return {"key": task.point.key, "values": task.point.values, "seed": task.point.seed,
                "status": outcome.status, "reason": outcome.reason, "run_id": outcome.run_id,
                "run_dir": str(outcome.run_dir.relative_to(self.dir.path)), "wall_s": round(outcome.wall_s, 3),
                "kpis": flatten_kpis(outcome.kpis),
                "finished": datetime.now(UTC).isoformat(timespec="seconds")}

    def _more_seeds(self, points: list[Point]) -> list[Point]:
        """Points for the extra seeds that grid points short of ``repeat_until.min_tasks`` need.

        Counts every recorded run of a grid point, also those of seeds added by an earlier
        invocation of a resumed sweep."""
        rule = self.spec.repeat_until
        if rule is None:
            return []
        seeds: dict[str, set[int]] = {}
        values: dict[str, dict[str, Any]] = {}
        for p in points:
            seeds.setdefault(p.grid_id, set()).add(p.seed)
            values[p.grid_id] = p.values
        tasks: dict[str, list[int]] = {g: [] for g in seeds}
        for r in self.dir.records():
            g = json.dumps(r["values"], sort_keys=True)
            if g in seeds:
                seeds[g].add(r["seed"])
                if r["status"] == RunState.COMPLETED:
                    tasks[g].append(int(r["kpis"].get("tasks") or 0))
        base = base_path(self.spec.base, self.scenarios_dir, self.allow_paths)
        extra: list[Point] = []
        for g, used in seeds.items():
            have, room = sum(tasks[g]), rule.max_seeds - len(used)
            if have >= rule.min_tasks or room <= 0 or not tasks[g]:
                continue
            per_seed = have / len(tasks[g])
            need = math.ceil((rule.min_tasks - have) / per_seed) if per_seed > 0 else 1
            # The next seeds after the highest, then the lowest free ones (seeds end at SEED_LIMIT).
            free = itertools.chain(range(max(used) + 1, SEED_LIMIT), range(SEED_LIMIT))
            extra += [make_point(self.spec, base, values[g], s)
                      for s in itertools.islice((s for s in free if s not in used), min(need, room))]
        return extra

    def _series_of(self, values: dict[str, Any]) -> str:
        """The series a grid combination belongs to: its values other than the load."""
        return json.dumps({k: v for k, v in values.items() if k != self.spec.capacity.x}, sort_keys=True)

    def _waves(self, points: list[Point]) -> list[list[Point]]:
        """The points in the order they run: all at once, or with ``capacity.stop_after`` one
        load at a time, ascending, so that a series can stop before its larger loads."""
        if self.spec.capacity.stop_after is None:
            return [points]
        x = self.spec.capacity.x
        loads = sorted({p.values[x] for p in points})
        return [[p for p in points if p.values[x] == load] for load in loads]

    def _stopped_series(self, wave: list[Point]) -> set[str]:
        """Series whose last ``capacity.stop_after`` recorded loads below the ``wave``'s all missed the
        lowest threshold (task success pooled over a load's completed runs). Only loads below it
        count: a resumed sweep with more seeds runs them at every load below the stop its series
        reaches with them, not only where the fewer seeds had reached (and ``repeat_until``'s
        extra seeds likewise, each round)."""
        rule = self.spec.capacity
        if rule.stop_after is None or not wave:
            return set()
        load = wave[0].values[rule.x]
        placed: dict[str, dict[Any, list[int]]] = {}
        for r in self.dir.records():
            if r["status"] != RunState.COMPLETED or rule.x not in r["values"] or not r["values"][rule.x] < load:
                continue
            pt = placed.setdefault(self._series_of(r["values"]), {}).setdefault(r["values"][rule.x], [0, 0])
            pt[0] += int(r["kpis"].get("tasks_placed") or 0)
            pt[1] += int(r["kpis"].get("tasks") or 0)
        lowest = min(rule.thresholds)
        stopped = set()
        for series, by_load in placed.items():
            tail = [placed_n / tasks for _, (placed_n, tasks) in sorted(by_load.items()) if tasks][-rule.stop_after:]
            if len(tail) == rule.stop_after and all(rate < lowest for rate in tail):
                stopped.add(series)
        return stopped

    def _run_points(self, todo: list[Point], points: list[Point], executor: Executor,
                    on_start: Callable[[PointTask], None], on_done: Callable[[PointTask, PointOutcome], None],
                    cancel: threading.Event) -> None:
        """Run ``todo`` wave by wave, then the extra seeds ``repeat_until`` asks for (appended to
        ``points``), until nothing is left or the sweep is cancelled."""
        prog = self.progress
        passed: list[Point] = []  # passed over: their series had stopped
        # At least one round, also with nothing left to run: a sweep resumed after its base
        # points still adds the seeds ``repeat_until`` asks for.
        first = True
        while (todo or first) and not cancel.is_set():
            first = False
            for wave in self._waves(todo):
                stopped = self._stopped_series(wave)
                run = [p for p in wave if self._series_of(p.values) not in stopped]
                passed += [p for p in wave if self._series_of(p.values) in stopped]
                with prog.lock:
                    prog.total -= len(wave) - len(run)
                    prog.passed_over += len(wave) - len(run)
                if run:
                    executor.run([self._task(p) for p in run], on_start, on_done, cancel)
                if cancel.is_set():
                    return
            extra = [p for p in self._more_seeds(points) if p.key not in self.dir.completed_keys()]
            points += extra
            # Seeds added to a series may lift the loads that stopped it: what was passed over is
            # looked at again, in its wave (a round that adds no seed ends the sweep).
            again, passed = (passed, []) if extra else ([], passed)
            todo = extra + again
            with prog.lock:
                prog.total += len(todo)
                prog.passed_over -= len(again)

    def run(self, executor: Executor, cancel: threading.Event | None = None,
            on_event: Callable[[str, dict[str, Any]], None] | None = None) -> dict[str, Any]:
        """Run the sweep to its end (or until cancelled); returns the capacity record."""
        self.dir.hold()  # before anything is written: a busy directory is left as it is
        try:
            return self._run(executor, cancel or threading.Event(), on_event or (lambda kind, data: None))
        finally:
            self.dir.release()

    def _run(self, executor: Executor, cancel: threading.Event,
             emit: Callable[[str, dict[str, Any]], None]) -> dict[str, Any]:
        # A resumed sweep's meta keeps its identity, not the end of its previous invocation.
        last = {k: v for k, v in self.dir.meta().items()
                if k not in ("finished", "reason", "wall_s", "points", "passed_over")}
        meta = {**last, "state": RunState.RUNNING, "executor": executor.name,
                "started": datetime.now(UTC).isoformat(timespec="seconds")}
        self.dir.write_meta(meta)
        wall0 = time.monotonic()
        points = expand(self.spec, self.scenarios_dir, allow_paths=self.allow_paths)
        completed = self.dir.completed_keys()
        prog = self.progress
        prog.total = len(points)
        prog.skipped = sum(1 for p in points if p.key in completed)
        record_lock = threading.Lock()

        def on_start(task: PointTask) -> None:
            with prog.lock:
                prog.in_flight[task.run_id] = InFlight(task.point.label(), task.progress_file, time.monotonic())
            emit("point_started", {"run_id": task.run_id, "point": task.point.label()})

        def on_done(task: PointTask, outcome: PointOutcome) -> None:
            rec = self._record(task, outcome)
            with record_lock:
                self.dir.append(rec)
            with prog.lock:
                prog.in_flight.pop(task.run_id, None)
                prog.done += 1
                prog.failed += outcome.status != RunState.COMPLETED
                prog.point_wall.append(outcome.wall_s)
            if task.progress_file is not None:
                task.progress_file.unlink(missing_ok=True)
            emit("point_done", rec)

        todo = [p for p in points if p.key not in completed]
        # An executor that holds a cluster (Ray) keeps it up across the waves.
        session = getattr(executor, "session", contextlib.nullcontext)
        try:
            with session():
                self._run_points(todo, points, executor, on_start, on_done, cancel)
        except Exception as exc:  # the sweep ends failed, saying why, never left "running"
            meta.update(state=RunState.FAILED, reason=f"{type(exc).__name__}: {exc}",
                        finished=datetime.now(UTC).isoformat(timespec="seconds"),
                        wall_s=round(time.monotonic() - wall0, 1))
            self.dir.write_meta(meta)
            raise
        state = RunState.CANCELLED if cancel.is_set() else RunState.COMPLETED
        meta.update(state=state, finished=datetime.now(UTC).isoformat(timespec="seconds"),
                    wall_s=round(time.monotonic() - wall0, 1), points=len(points),
                    passed_over=prog.passed_over)
        self.dir.write_meta(meta)
        cap = rebuild(self.dir.path)
        emit("sweep_done", {"state": state, "capacity": cap})
        return cap

