"""The job store: every run and sweep the coordinator accepted, in one SQLite table (WAL mode).

Writes are single statements, each its own transaction, so a crash loses nothing already
recorded. A store written by an older coordinator (a ``runs`` and a ``sweeps`` table) is moved
into the ``jobs`` table when it is opened.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from enum import StrEnum
from pathlib import Path
from typing import Any

from coordinator.run_state import ACTIVE, RunState


class JobKind(StrEnum):
    RUN = "run"
    SWEEP = "sweep"



_SCHEMA = """
CREATE TABLE IF NOT EXISTS jobs (
    job_id TEXT PRIMARY KEY,
    kind TEXT NOT NULL,
    name TEXT NOT NULL,
    request_json TEXT NOT NULL,
    state TEXT NOT NULL,
    reason TEXT,
    created_s REAL NOT NULL,
    started_s REAL,
    finished_s REAL,
    sim_time_s REAL,
    real_time_factor REAL,
    kpis_json TEXT,
    dir TEXT NOT NULL
)
"""
# Tables of the store before it held runs and sweeps in one, and how their rows become jobs.
_OLD_TABLES = {
    "runs": "SELECT run_id, 'run', scenario, config_json, status, reason, created_s, started_s, finished_s, "
            "sim_time_s, real_time_factor, kpis_json, COALESCE(results_dir, '') FROM runs",
    "sweeps": "SELECT sweep_id, 'sweep', name, spec_json, state, reason, created_s, started_s, finished_s, "
              "NULL, NULL, NULL, sweep_dir FROM sweeps",
}


class JobStore:
    """The ``jobs`` table. ``request_json`` holds a run's scenario or a sweep's spec; ``dir`` a
    run's results directory or a sweep's directory."""

    def __init__(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(str(path), check_same_thread=False, isolation_level=None, timeout=30)
        self._db.row_factory = sqlite3.Row
        self._lock = threading.Lock()
        with self._lock:
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.execute(_SCHEMA)
            self._adopt_old_tables()

    def _adopt_old_tables(self) -> None:
        names = {r[0] for r in self._db.execute("SELECT name FROM sqlite_master WHERE type='table'")}
        for table, select in _OLD_TABLES.items():
            if table in names:
                self._db.execute("BEGIN")
                self._db.execute(f"INSERT OR IGNORE INTO jobs {select}")
                self._db.execute(f"DROP TABLE {table}")
                self._db.execute("COMMIT")

    def add(self, job_id: str, kind: JobKind, name: str, request: dict[str, Any], job_dir: Path) -> None:
        with self._lock:
            self._db.execute(
                "INSERT INTO jobs (job_id, kind, name, request_json, state, created_s, dir) VALUES (?,?,?,?,?,?,?)",
                (job_id, kind.value, name, json.dumps(request), RunState.PENDING.value, time.time(), str(job_dir)))

    def set_running(self, job_id: str) -> None:
        with self._lock:
            self._db.execute("UPDATE jobs SET state=?, started_s=COALESCE(started_s, ?) WHERE job_id=?",
                             (RunState.RUNNING.value, time.time(), job_id))

    def set_progress(self, job_id: str, sim_time_s: float, rtf: float) -> None:
        with self._lock:
            self._db.execute("UPDATE jobs SET sim_time_s=?, real_time_factor=? WHERE job_id=?",
                             (sim_time_s, rtf, job_id))

    def finish(self, job_id: str, state: RunState | str, reason: str | None,
               kpis: dict[str, Any] | None = None) -> None:
        """The job's end; a run's KPIs also give its simulated time and real-time factor."""
        kpis = kpis or {}
        with self._lock:
            self._db.execute(
                "UPDATE jobs SET state=?, reason=?, finished_s=?, kpis_json=?, "
                "sim_time_s=COALESCE(?, sim_time_s), real_time_factor=COALESCE(?, real_time_factor) "
                "WHERE job_id=?",
                (str(state), reason, time.time(), json.dumps(kpis, default=str) if kpis else None,
                 kpis.get("sim_time_s"), kpis.get("real_time_factor"), job_id))

    def fail_active_runs(self, reason: str) -> list[tuple[str, str]]:
        """Mark the runs a previous coordinator left unfinished as failed: (run id, results
        directory) of each, for their records to be closed."""
        with self._lock:
            rows = self._db.execute("SELECT job_id, dir FROM jobs WHERE kind='run' AND state IN (?,?)",
                                    ACTIVE).fetchall()
            self._db.execute("UPDATE jobs SET state=?, reason=?, finished_s=? WHERE kind='run' AND state IN (?,?)",
                             (RunState.FAILED.value, reason, time.time(), *ACTIVE))
        return [(str(r[0]), str(r[1])) for r in rows]

    def get(self, job_id: str, kind: JobKind | None = None) -> dict[str, Any] | None:
        with self._lock:
            row = self._db.execute("SELECT * FROM jobs WHERE job_id=?", (job_id,)).fetchone()
        if row is None or (kind is not None and row["kind"] != kind.value):
            return None
        return _row(row)

    def list(self, kind: JobKind, states: tuple[str, ...] | None = None, limit: int = 200) -> list[dict[str, Any]]:
        """Newest first; with ``states``, only those (every one of them, oldest first)."""
        with self._lock:
            if states:
                rows = self._db.execute(
                    f"SELECT * FROM jobs WHERE kind=? AND state IN ({','.join('?' * len(states))}) "
                    "ORDER BY created_s", (kind.value, *states)).fetchall()
            else:
                rows = self._db.execute("SELECT * FROM jobs WHERE kind=? ORDER BY created_s DESC LIMIT ?",
                                        (kind.value, limit)).fetchall()
        return [_row(r) for r in rows]

    def close(self) -> None:
        with self._lock:
            self._db.close()


def _row(row: sqlite3.Row) -> dict[str, Any]:
    d = dict(row)
    d["request"] = json.loads(d.pop("request_json"))
    kpis = d.pop("kpis_json")
    d["kpis"] = json.loads(kpis) if kpis else None
    return d
