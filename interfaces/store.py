"""The run store: one SQLite database (WAL mode) recording every run's request, state and KPIs.

Writes are single statements in their own transaction, so a crash loses nothing already
recorded; a run left ``pending`` or ``running`` by a coordinator that died is marked failed when
the next coordinator opens the store.
"""

from __future__ import annotations

import json
import sqlite3
import threading
import time
from pathlib import Path
from typing import Any

_SCHEMA = """
CREATE TABLE IF NOT EXISTS runs (
    run_id TEXT PRIMARY KEY,
    scenario TEXT NOT NULL,
    config_json TEXT NOT NULL,
    status TEXT NOT NULL,
    reason TEXT,
    created_s REAL NOT NULL,
    started_s REAL,
    finished_s REAL,
    sim_time_s REAL,
    real_time_factor REAL,
    kpis_json TEXT,
    results_dir TEXT
)
"""

ACTIVE = ("pending", "running")


# Why a run a previous coordinator left unfinished failed.
ORPHAN_REASON = "coordinator stopped during the run"


class RunStore:
    def __init__(self, path: Path) -> None:
        path.parent.mkdir(parents=True, exist_ok=True)
        self._db = sqlite3.connect(str(path), check_same_thread=False, isolation_level=None)
        self._db.row_factory = sqlite3.Row
        self._lock = threading.Lock()
        with self._lock:
            self._db.execute("PRAGMA journal_mode=WAL")
            self._db.execute("PRAGMA synchronous=NORMAL")
            self._db.execute(_SCHEMA)

    def reap_orphans(self) -> list[tuple[str, str]]:
        """Mark runs a previous coordinator left unfinished as failed; their (run id, results
        directory), for their records to be closed."""
        with self._lock:
            rows = self._db.execute(
                "SELECT run_id, results_dir FROM runs WHERE status IN ('pending','running')").fetchall()
            self._db.execute(
                "UPDATE runs SET status='failed', reason=?, finished_s=? WHERE status IN ('pending','running')",
                (ORPHAN_REASON, time.time()))
            return [(str(r[0]), str(r[1])) for r in rows]

    def add(self, run_id: str, scenario: str, config: dict[str, Any], results_dir: str) -> None:
        with self._lock:
            self._db.execute(
                "INSERT INTO runs (run_id, scenario, config_json, status, created_s, results_dir) "
                "VALUES (?, ?, ?, 'pending', ?, ?)",
                (run_id, scenario, json.dumps(config), time.time(), results_dir))

    def set_running(self, run_id: str) -> None:
        with self._lock:
            self._db.execute("UPDATE runs SET status='running', started_s=? WHERE run_id=?", (time.time(), run_id))

    def set_progress(self, run_id: str, sim_time_s: float, rtf: float) -> None:
        with self._lock:
            self._db.execute("UPDATE runs SET sim_time_s=?, real_time_factor=? WHERE run_id=?",
                             (sim_time_s, rtf, run_id))

    def finish(self, run_id: str, status: str, reason: str | None, kpis: dict[str, Any]) -> None:
        with self._lock:
            self._db.execute(
                "UPDATE runs SET status=?, reason=?, finished_s=?, kpis_json=?, sim_time_s=?, "
                "real_time_factor=? WHERE run_id=?",
                (status, reason, time.time(), json.dumps(kpis, default=str), kpis.get("sim_time_s"),
                 kpis.get("real_time_factor"), run_id))

    def get(self, run_id: str) -> dict[str, Any] | None:
        with self._lock:
            row = self._db.execute("SELECT * FROM runs WHERE run_id=?", (run_id,)).fetchone()
        return _row(row) if row else None

    def list(self, limit: int = 100) -> list[dict[str, Any]]:
        with self._lock:
            rows = self._db.execute("SELECT * FROM runs ORDER BY created_s DESC LIMIT ?", (limit,)).fetchall()
        return [_row(r) for r in rows]

    def close(self) -> None:
        with self._lock:
            self._db.close()


def _row(row: sqlite3.Row) -> dict[str, Any]:
    d = dict(row)
    d["config"] = json.loads(d.pop("config_json"))
    kp = d.pop("kpis_json")
    d["kpis"] = json.loads(kp) if kp else None
    return d
