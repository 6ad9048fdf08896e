"""Sweeps as a service: a queue of sweeps run one after another by the engine, their state in
SQLite (WAL), for the coordinator's REST API.

A sweep survives its coordinator: at start, every sweep left ``pending`` or ``running`` is queued
again and resumed from its directory, where the completed points stay and the points that were in
flight (they died with the coordinator) run again; no point is recorded twice (experiments.sweep).
"""

from __future__ import annotations

import json
import queue
import sqlite3
import threading
import time
from collections.abc import Callable
from contextlib import nullcontext
from pathlib import Path
from typing import Any

from experiments.executors import Executor, LocalExecutor
from experiments.points import expand
from experiments.report import load_sweep_spec
from experiments.spec import SweepSpec
from experiments.sweep import Sweep

_SCHEMA = """
CREATE TABLE IF NOT EXISTS sweeps (
    sweep_id TEXT PRIMARY KEY,
    name TEXT NOT NULL,
    spec_json TEXT NOT NULL,
    state TEXT NOT NULL,
    reason TEXT,
    created_s REAL NOT NULL,
    started_s REAL,
    finished_s REAL,
    sweep_dir TEXT NOT NULL
)
"""
ACTIVE = ("pending", "running")


class SweepStore:
    """The sweeps table; single statements, each its own transaction."""

    def __init__(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(str(path), check_same_thread=False, isolation_level=None, timeout=30)
        self._db.row_factory = sqlite3.Row
        self._lock = threading.Lock()
        with self._lock:
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.execute(_SCHEMA)

    def add(self, sweep_id: str, spec: SweepSpec, sweep_dir: Path) -> None:
        with self._lock:
            self._db.execute(
                "INSERT INTO sweeps (sweep_id, name, spec_json, state, created_s, sweep_dir) VALUES (?,?,?,?,?,?)",
                (sweep_id, spec.name, spec.model_dump_json(), "pending", time.time(), str(sweep_dir)))

    def set_state(self, sweep_id: str, state: str, reason: str | None = None) -> None:
        now = time.time()
        with self._lock:
            if state == "running":
                self._db.execute("UPDATE sweeps SET state=?, started_s=COALESCE(started_s, ?) WHERE sweep_id=?",
                                 (state, now, sweep_id))
            else:
                self._db.execute("UPDATE sweeps SET state=?, reason=?, finished_s=? WHERE sweep_id=?",
                                 (state, reason, now, sweep_id))

    def get(self, sweep_id: str) -> dict[str, Any] | None:
        with self._lock:
            row = self._db.execute("SELECT * FROM sweeps WHERE sweep_id=?", (sweep_id,)).fetchone()
        return dict(row) if row else None

    def list(self, states: tuple[str, ...] | None = None, limit: int = 200) -> list[dict[str, Any]]:
        with self._lock:
            if states:
                rows = self._db.execute(
                    f"SELECT * FROM sweeps WHERE state IN ({','.join('?' * len(states))}) ORDER BY created_s",
                    states).fetchall()
            else:
                rows = self._db.execute("SELECT * FROM sweeps ORDER BY created_s DESC LIMIT ?", (limit,)).fetchall()
        return [dict(r) for r in rows]

    def close(self) -> None:
        with self._lock:
            self._db.close()


class SweepService:
    """Owns the sweep queue and its worker thread.

    ``busy``: a lock shared with whatever else runs simulations on this host (the single-run
    worker), so that a small host runs one thing at a time."""

    def __init__(self, db_path: Path, root: Path, scenarios_dir: Path, jobs: int = 1,
                 make_executor: Callable[[], Executor] | None = None, busy: Any = None) -> None:
        self.root = root
        self.scenarios_dir = scenarios_dir
        self.store = SweepStore(db_path)
        self.make_executor = make_executor or (lambda: LocalExecutor(jobs))
        self.jobs = jobs
        self.busy = busy if busy is not None else nullcontext()
        self.queue: queue.SimpleQueue[str | None] = queue.SimpleQueue()
        self.cancels: dict[str, threading.Event] = {}
        self.running: dict[str, Sweep] = {}
        self.on_point_done: Callable[[str], None] | None = None  # called with each finished point's state
        self._points: dict[str, list[dict[str, Any]]] = {}
        for row in self.store.list(ACTIVE):  # left by a coordinator that stopped: resume them
            self.cancels[row["sweep_id"]] = threading.Event()
            self.queue.put(row["sweep_id"])
        self.worker = threading.Thread(target=self._work, daemon=True, name="sweeps")
        self.worker.start()

    def queued(self) -> int:
        return len(self.store.list(ACTIVE))

    def submit(self, spec: SweepSpec) -> dict[str, Any]:
        sweep = Sweep.create(spec, self.root, scenarios_dir=self.scenarios_dir, allow_paths=False)
        sid = sweep.sweep_id
        self.store.add(sid, spec, sweep.dir.path)
        self.cancels[sid] = threading.Event()
        self.queue.put(sid)
        return {"sweep_id": sid, "state": "pending", "points": len(self.points(sid))}

    def cancel(self, sweep_id: str) -> bool:
        ev = self.cancels.get(sweep_id)
        if ev is None:
            return False
        ev.set()
        return True

    def _work(self) -> None:
        while True:
            sid = self.queue.get()
            if sid is None:
                return
            row = self.store.get(sid)
            cancel = self.cancels.get(sid, threading.Event())
            if row is None:
                continue
            if cancel.is_set():
                self.store.set_state(sid, "cancelled", "cancelled before it started")
                self.cancels.pop(sid, None)
                continue
            try:
                with self.busy:
                    sweep = Sweep(load_sweep_spec(Path(row["sweep_dir"])), Path(row["sweep_dir"]),
                                  self.scenarios_dir, allow_paths=False)
                    self.running[sid] = sweep
                    self.store.set_state(sid, "running")
                    sweep.run(self.make_executor(), cancel, self._event)
                    state = sweep.dir.meta().get("state", "completed")
                    self.store.set_state(sid, state, "cancelled by the user" if state == "cancelled" else None)
            except Exception as exc:  # the worker must survive a broken sweep
                self.store.set_state(sid, "failed", f"coordinator error: {type(exc).__name__}: {exc}")
            finally:
                self.running.pop(sid, None)
                self.cancels.pop(sid, None)

    def _event(self, kind: str, data: dict[str, Any]) -> None:
        if kind == "point_done" and self.on_point_done is not None:
            self.on_point_done(data["status"])

    def points(self, sweep_id: str) -> list[dict[str, Any]]:
        """Every point of the sweep's grid and base seeds: values, seed, key (cached)."""
        if sweep_id not in self._points:
            row = self.store.get(sweep_id)
            if row is None:
                return []
            spec = SweepSpec.model_validate_json(row["spec_json"])
            self._points[sweep_id] = [{"values": p.values, "seed": p.seed, "key": p.key}
                                      for p in expand(spec, self.scenarios_dir, allow_paths=False)]
        return self._points[sweep_id]

    def describe(self, sweep_id: str) -> dict[str, Any] | None:
        """State, progress, per-point state and KPIs so far, capacity once done."""
        row = self.store.get(sweep_id)
        if row is None:
            return None
        sweep_dir = Path(row["sweep_dir"])
        from experiments.records import SweepDir

        records = {r["key"]: r for r in SweepDir(sweep_dir).records()}
        sweep = self.running.get(sweep_id)
        snap = sweep.progress.snapshot(self.jobs) if sweep is not None else None
        in_flight = {c["point"]: c for c in (snap or {}).get("running", [])}
        points = []
        known = set()
        for p in self.points(sweep_id):
            known.add(p["key"])
            points.append(_point_state(p, records.get(p["key"]), in_flight))
        # Seeds added by repeat_until are not in the base grid: list them from the records.
        for key, rec in records.items():
            if key not in known:
                points.append(_point_state({"values": rec["values"], "seed": rec["seed"], "key": key}, rec, {}))
        cap_path = sweep_dir / "capacity.json"
        done = sum(1 for p in points if p["state"] in ("completed", "failed", "timed_out", "cancelled"))
        return {
            "sweep_id": sweep_id, "name": row["name"], "state": row["state"], "reason": row["reason"],
            "created_s": row["created_s"], "started_s": row["started_s"], "finished_s": row["finished_s"],
            "spec": json.loads(row["spec_json"]),
            "progress": {"points_total": max(len(points), snap["total"] if snap else 0), "points_done": done,
                         "points_failed": sum(1 for p in points if p["state"] not in ("completed", "pending", "running")),
                         "eta_s": snap["eta_s"] if snap else None},
            "points": points,
            "capacity": json.loads(cap_path.read_text()) if row["state"] not in ACTIVE and cap_path.is_file() else None,
        }

    def close(self) -> None:
        for ev in self.cancels.values():
            ev.set()
        self.queue.put(None)
        self.worker.join(timeout=60)
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
        out.update(state="running", sim_time_s=in_flight[label]["sim_time_s"])
    else:
        out.update(state="pending")
    return out
