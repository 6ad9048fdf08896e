"""The coordinator's jobs: one pool of slots that runs and sweep points share, runs first; one
store, adopting the two tables an older coordinator wrote."""

from __future__ import annotations

import sqlite3
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from coordinator.run import RunResult
from experiments import executors
from experiments.executors import LocalExecutor
from experiments.job_store import JobKind, JobStore
from experiments.jobs import JobService, TooMuchWork
from experiments.point_runs import PointOutcome, PointTask
from experiments.slots import POINT_PRIORITY, RUN_PRIORITY, Slots
from experiments.spec import parse_spec
from experiments.sweep import Sweep
from scenario.schema import Scenario, load_scenario

ROOT = Path(__file__).parents[2]



def test_a_freed_slot_goes_to_a_run_before_waiting_points() -> None:
    slots = Slots(1)
    order: list[str] = []
    release = threading.Event()

    def take(name: str, priority: int) -> None:
        with slots.take(priority) as got:
            assert got
            order.append(name)
            if name == "first":
                release.wait(5)

    first = threading.Thread(target=take, args=("first", POINT_PRIORITY))
    first.start()
    while slots.in_use() == 0:
        time.sleep(0.01)
    waiters = [threading.Thread(target=take, args=(n, p)) for n, p in
               (("point 1", POINT_PRIORITY), ("point 2", POINT_PRIORITY), ("run", RUN_PRIORITY))]
    for w in waiters:
        w.start()
        time.sleep(0.05)  # in this order
    release.set()
    for t in [first, *waiters]:
        t.join(5)
    assert order == ["first", "run", "point 1", "point 2"]


def test_a_cancelled_waiter_leaves_the_line() -> None:
    slots = Slots(1)
    cancel = threading.Event()
    with slots.take(RUN_PRIORITY) as got:
        assert got
        cancel.set()
        with slots.take(POINT_PRIORITY, cancel) as waited:
            assert not waited
    with slots.take(POINT_PRIORITY) as got:  # the line is empty again
        assert got and slots.in_use() == 1


class Timeline:
    """When each run and each sweep point started and ended."""

    def __init__(self) -> None:
        self.events: list[tuple[str, str]] = []
        self.lock = threading.Lock()

    def add(self, what: str, name: str) -> None:
        with self.lock:
            self.events.append((what, name))


def test_a_run_submitted_during_a_sweep_goes_between_its_points(tmp_path: Path,
                                                                monkeypatch: pytest.MonkeyPatch) -> None:
    timeline = Timeline()

    def point(task: PointTask, procs: Any = None) -> PointOutcome:  # stands in for a `cosim5g run` process
        timeline.add("start", task.point.label())
        time.sleep(0.3)
        timeline.add("end", task.point.label())
        return PointOutcome(task.point.key, task.run_id, "completed", None, task.runs_dir / task.run_id, 0.3,
                            {"tasks": 0})

    def execute(sc: Scenario, results_root: Path, on_progress: Any = None, cancel: Any = None,
                run_id: str | None = None) -> RunResult:
        assert run_id is not None
        timeline.add("start", "run")
        time.sleep(0.1)
        timeline.add("end", "run")
        return RunResult(run_id, "completed", results_root / run_id, {"sim_time_s": 1.0})

    monkeypatch.setattr(executors, "run_point", point)
    jobs = JobService(tmp_path / "jobs.db", tmp_path / "runs", tmp_path / "sweeps", ROOT / "configs" / "scenarios",
                      slots=1, max_queued=4, execute=execute, make_executor=lambda s: LocalExecutor(1, slots=s))
    try:
        spec = parse_spec({"name": "s", "base": "baseline", "seeds": 1, "grid": {"loops": [2, 4, 6, 8]},
                           "set": {"duration_s": 5, "detailed_loops": 0}}, ROOT / "configs" / "scenarios",
                          allow_paths=False)
        sweep_id, points = jobs.submit_sweep(spec)
        assert points == 4
        while not timeline.events:
            time.sleep(0.02)
        run_id = jobs.submit_run(load_scenario(ROOT / "configs" / "scenarios" / "smoke.yaml"))
        deadline = time.monotonic() + 30
        while jobs.queued() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert jobs.store.get(run_id, JobKind.RUN)["state"] == "completed"
        assert jobs.store.get(sweep_id, JobKind.SWEEP)["state"] == "completed"
    finally:
        jobs.close()
    starts = [name for what, name in timeline.events if what == "start"]
    # The run waited for the point in flight only, and nothing ran beside anything else.
    assert starts.index("run") == 1, starts
    assert all(timeline.events[i][0] == "start" and timeline.events[i + 1] == ("end", timeline.events[i][1])
               for i in range(0, len(timeline.events), 2)), timeline.events


def test_the_queue_limit_counts_runs_and_sweeps_together(tmp_path: Path) -> None:
    hold = threading.Event()

    def execute(sc: Scenario, results_root: Path, on_progress: Any = None, cancel: Any = None,
                run_id: str | None = None) -> RunResult:
        assert run_id is not None and cancel is not None
        while not (hold.is_set() or cancel.is_set()):
            time.sleep(0.01)
        return RunResult(run_id, "completed", results_root / run_id, {})

    jobs = JobService(tmp_path / "jobs.db", tmp_path / "runs", tmp_path / "sweeps", ROOT / "configs" / "scenarios",
                      slots=1, max_queued=2, execute=execute)
    try:
        smoke = load_scenario(ROOT / "configs" / "scenarios" / "smoke.yaml")
        first = jobs.submit_run(smoke)
        jobs.submit_run(smoke)
        with pytest.raises(TooMuchWork, match=r"2 runs and sweeps .* max_queued"):
            jobs.submit_run(smoke)
        assert jobs.cancel(first)
        deadline = time.monotonic() + 10
        while jobs.queued() > 1 and time.monotonic() < deadline:
            time.sleep(0.02)
        jobs.submit_run(smoke)  # the cancelled run freed its place
        hold.set()
    finally:
        jobs.close()


def test_a_store_of_an_older_coordinator_is_adopted(tmp_path: Path) -> None:
    db = sqlite3.connect(tmp_path / "old.db")
    db.execute("CREATE TABLE runs (run_id TEXT PRIMARY KEY, scenario TEXT NOT NULL, config_json TEXT NOT NULL, "
               "status TEXT NOT NULL, reason TEXT, created_s REAL NOT NULL, started_s REAL, finished_s REAL, "
               "sim_time_s REAL, real_time_factor REAL, kpis_json TEXT, results_dir TEXT)")
    db.execute("CREATE TABLE sweeps (sweep_id TEXT PRIMARY KEY, name TEXT NOT NULL, spec_json TEXT NOT NULL, "
               "state TEXT NOT NULL, reason TEXT, created_s REAL NOT NULL, started_s REAL, finished_s REAL, "
               "sweep_dir TEXT NOT NULL)")
    db.execute("INSERT INTO runs VALUES ('r1', 'smoke', '{\"duration_s\": 2}', 'completed', NULL, 1, 2, 3, 2.0, "
               "1.5, '{\"tasks\": 3}', '/r/r1')")
    db.execute("INSERT INTO sweeps VALUES ('s1', 'quick', '{\"name\": \"quick\"}', 'running', NULL, 4, 5, NULL, '/s/s1')")
    db.commit()
    db.close()
    store = JobStore(tmp_path / "old.db")
    run = store.get("r1", JobKind.RUN)
    assert run is not None and (run["state"], run["request"], run["kpis"], run["dir"]) == (
        "completed", {"duration_s": 2}, {"tasks": 3}, "/r/r1")
    [sweep] = store.list(JobKind.SWEEP, ("running",))
    assert (sweep["job_id"], sweep["request"], sweep["dir"]) == ("s1", {"name": "quick"}, "/s/s1")
    assert store.get("s1", JobKind.RUN) is None  # a sweep is no run
    store.close()
    tables = {r[0] for r in sqlite3.connect(tmp_path / "old.db").execute("SELECT name FROM sqlite_master")}
    assert "runs" not in tables and "sweeps" not in tables


def fake_point(tasks: int, timeline: Timeline | None = None, hold_s: float = 0.0) -> Any:
    """Stands in for a `cosim5g run` process: a completed run of ``tasks`` tasks."""

    def point(task: PointTask, procs: Any = None) -> PointOutcome:
        if timeline is not None:
            timeline.add("start", task.point.label())
        time.sleep(hold_s)
        return PointOutcome(task.point.key, task.run_id, "completed", None, task.runs_dir / task.run_id, hold_s,
                            {"tasks": tasks, "tasks_placed": tasks})

    return point


SCENARIOS = ROOT / "configs" / "scenarios"


def service(tmp_path: Path) -> JobService:
    """A coordinator's job service on ``tmp_path``, one slot; a second one takes over its store."""
    return JobService(tmp_path / "jobs.db", tmp_path / "runs", tmp_path / "sweeps", SCENARIOS, slots=1,
                      make_executor=lambda s: LocalExecutor(1, slots=s))


def loads_sweep(loads: list[int], **more: Any) -> Any:
    """A sweep of the baseline over ``loads`` loops, as a request gives it."""
    return parse_spec({"name": "s", "base": "baseline", "grid": {"loops": loads},
                       "set": {"duration_s": 5, "detailed_loops": 0}, **more}, SCENARIOS, allow_paths=False)


def test_a_sweep_stopped_with_the_service_is_resumed_by_the_next_start(tmp_path: Path,
                                                                       monkeypatch: pytest.MonkeyPatch) -> None:
    timeline = Timeline()
    monkeypatch.setattr(executors, "run_point", fake_point(1, timeline, hold_s=0.3))
    jobs = service(tmp_path)
    sweep_id, _ = jobs.submit_sweep(loads_sweep([2, 4, 6, 8]))
    while not timeline.events:
        time.sleep(0.02)
    jobs.close()  # the service stops (SIGTERM) while the sweep runs
    jobs = service(tmp_path)  # the next start
    try:
        deadline = time.monotonic() + 30
        while jobs.queued() and time.monotonic() < deadline:
            time.sleep(0.05)
        row = jobs.store.get(sweep_id, JobKind.SWEEP)
        assert row["state"] == "completed" and row["reason"] is None
        assert sorted(p["values"]["loops"] for p in jobs.describe(sweep_id)["points"]) == [2, 4, 6, 8]
    finally:
        jobs.close()


def test_a_sweep_resumed_after_its_base_points_still_adds_the_seeds_it_needs(tmp_path: Path,
                                                                             monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(executors, "run_point", fake_point(5))
    spec = loads_sweep([1, 2], repeat_until={"min_tasks": 12, "max_seeds": 5})
    sweep = Sweep.create(spec, tmp_path, scenarios_dir=SCENARIOS)
    cancel = threading.Event()
    sweep.run(LocalExecutor(1), cancel, lambda kind, data: cancel.set() if kind == "point_done"
              and len(sweep.dir.records()) == 2 else None)  # cancelled once the base points are in
    assert sorted((r["values"]["loops"], r["seed"]) for r in sweep.dir.records()) == [(1, 1), (2, 1)]
    Sweep(spec, sweep.dir.path, SCENARIOS).run(LocalExecutor(1))  # resumed
    seeds = sorted((r["values"]["loops"], r["seed"]) for r in sweep.dir.records())
    assert seeds == [(1, 1), (1, 2), (1, 3), (2, 1), (2, 2), (2, 3)]


def test_a_sweep_that_raises_is_recorded_failed_with_its_reason(tmp_path: Path) -> None:
    class Broken(LocalExecutor):
        def run(self, *args: Any, **kwargs: Any) -> None:
            raise RuntimeError("no cluster here")

    sweep = Sweep.create(loads_sweep([1]), tmp_path, scenarios_dir=SCENARIOS)
    with pytest.raises(RuntimeError, match="no cluster here"):
        sweep.run(Broken(1))
    meta = sweep.dir.meta()
    assert meta["state"] == "failed" and meta["reason"] == "RuntimeError: no cluster here"


def test_points_a_completed_sweep_passed_over_are_said_so_and_not_counted(tmp_path: Path,
                                                                            monkeypatch: pytest.MonkeyPatch) -> None:
    def point(task: PointTask, procs: Any = None) -> PointOutcome:  # every load from 2 on misses every task
        placed = 5 if task.point.values["loops"] < 2 else 0
        return PointOutcome(task.point.key, task.run_id, "completed", None, task.runs_dir / task.run_id, 0.0,
                            {"tasks": 5, "tasks_placed": placed})

    monkeypatch.setattr(executors, "run_point", point)
    jobs = service(tmp_path)
    try:
        sweep_id, _ = jobs.submit_sweep(loads_sweep([1, 2, 3, 4], capacity={"x": "loops", "stop_after": 1}))
        deadline = time.monotonic() + 30
        while jobs.queued() and time.monotonic() < deadline:
            time.sleep(0.05)
        detail = jobs.describe(sweep_id)
        assert detail is not None and detail["state"] == "completed"
        assert [p["state"] for p in detail["points"]] == ["completed", "completed", "passed_over", "passed_over"]
        assert detail["progress"] | {"eta_s": None} == {"points_total": 2, "points_done": 2, "points_failed": 0,
                                                       "points_passed_over": 2, "eta_s": None}
    finally:
        jobs.close()


def test_a_sweep_whose_spec_no_longer_expands_is_described_from_its_records(tmp_path: Path) -> None:
    store = JobStore(tmp_path / "jobs.db")
    store.add("old", JobKind.SWEEP, "old", {"name": "old", "base": "renamed_since", "grid": {"loops": [1]}},
              tmp_path / "sweeps" / "old")
    store.finish("old", "completed", None, None)
    store.close()
    jobs = service(tmp_path)
    try:
        detail = jobs.describe("old")
        assert detail is not None and detail["points"] == [] and detail["state"] == "completed"
    finally:
        jobs.close()


def test_a_sweep_the_user_cancelled_stays_cancelled_when_the_service_stops_meanwhile(
        tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    timeline = Timeline()
    monkeypatch.setattr(executors, "run_point", fake_point(1, timeline, hold_s=1.0))
    jobs = service(tmp_path)
    sweep_id, _ = jobs.submit_sweep(loads_sweep([2, 4, 6]))
    while not timeline.events:
        time.sleep(0.02)
    assert jobs.cancel(sweep_id)
    time.sleep(0.1)
    jobs.close()  # the service stops while the cancelled sweep winds down
    jobs = service(tmp_path)
    try:
        time.sleep(0.5)
        row = jobs.store.get(sweep_id, JobKind.SWEEP)
        assert row["state"] == "cancelled" and not jobs.queued()
    finally:
        jobs.close()


def test_the_coordinators_gauges_follow_a_sweep_point_by_point(tmp_path: Path,
                                                               monkeypatch: pytest.MonkeyPatch) -> None:
    from prometheus_client import REGISTRY

    from interfaces.api import count_jobs

    def gauge(name: str) -> float | None:
        return REGISTRY.get_sample_value(f"cosim_coordinator_{name}")

    seen: list[tuple[float | None, float | None]] = []

    def point(task: PointTask, procs: Any = None) -> PointOutcome:
        seen.append((gauge("slots_busy"), gauge("sweep_points_remaining")))
        return PointOutcome(task.point.key, task.run_id, "completed", None, task.runs_dir / task.run_id, 0.0,
                            {"tasks": 1, "tasks_placed": 1})

    monkeypatch.setattr(executors, "run_point", point)
    jobs = service(tmp_path)
    count_jobs(jobs)
    try:
        sweep_id, _ = jobs.submit_sweep(loads_sweep([2, 4, 6]))
        deadline = time.monotonic() + 30
        while jobs.queued() and time.monotonic() < deadline:
            time.sleep(0.05)
        assert jobs.store.get(sweep_id, JobKind.SWEEP)["state"] == "completed"
        # A point holds the one slot while it runs; what is left falls as each point ends.
        assert seen == [(1.0, 3.0), (1.0, 2.0), (1.0, 1.0)]
        assert (gauge("slots_busy"), gauge("sweep_points_remaining")) == (0.0, 0.0)
    finally:
        jobs.close()
