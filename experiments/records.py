"""The sweep directory and its records (docs/architecture.md sec. 9, "Sweeps").

A point is appended to ``points.jsonl`` only once its run has ended, so a sweep killed at any
moment loses at most the points in flight; later lines for the same key win. One process at a
time runs a sweep directory (``SweepDir.hold``), so no point runs twice.
"""

from __future__ import annotations

import fcntl
import json
import os
from pathlib import Path
from typing import Any

import pyarrow as pa
import pyarrow.parquet as pq

from coordinator.run_state import RunState
from fabric.tables import write_json, write_table

# Bulky or per-loop KPI entries that stay in the run's kpis.json (per-loop ones are in loops.parquet).
SKIPPED_KPIS = ("federates", "log_tail", "camera_bitrate_mbps", "windows_trace", "results_dir")
LOCK_FILE = "run.lock"


class SweepBusy(RuntimeError):
    """Another runner (a process, or another thread of this one) holds the sweep directory."""


def flatten_kpis(kpis: dict[str, Any], prefix: str = "") -> dict[str, Any]:
    """Scalar KPIs with nested dicts as dotted keys (``ip_latency_ms.p99``); lists are left out."""
    out: dict[str, Any] = {}
    for k, v in kpis.items():
        if not prefix and k in SKIPPED_KPIS:
            continue
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out.update(flatten_kpis(v, key + "."))
        elif v is None or isinstance(v, str | int | float | bool):
            out[key] = v
    return out


class SweepDir:
    """Reads and appends a sweep directory's records."""

    def __init__(self, path: Path) -> None:
        self.path = path
        self.runs = path / "runs"
        self.configs = path / "configs"
        self.progress = path / "progress"
        self._lock_fd: int | None = None

    def hold(self) -> None:
        """Take the directory for this runner until ``release`` or the process ends (the kernel
        drops the lock of a dead process); raises ``SweepBusy``, naming the holder's pid, when
        another runner has it. Holding it twice is a no-op."""
        if self._lock_fd is not None:
            return
        fd = os.open(self.path / LOCK_FILE, os.O_RDWR | os.O_CREAT, 0o644)
        try:
            fcntl.flock(fd, fcntl.LOCK_EX | fcntl.LOCK_NB)
        except BlockingIOError:
            holder = os.pread(fd, 32, 0).decode(errors="replace").strip() or "unknown"
            os.close(fd)
            raise SweepBusy(f"sweep directory {self.path} is being run by another runner (pid {holder}): "
                            "wait for it to end or cancel it there, then resume") from None
        os.ftruncate(fd, 0)
        os.pwrite(fd, f"{os.getpid()}\n".encode(), 0)
        self._lock_fd = fd

    def release(self) -> None:
        if self._lock_fd is not None:
            os.close(self._lock_fd)  # closing the descriptor drops the lock
            self._lock_fd = None

    @property
    def log_path(self) -> Path:
        return self.path / "points.jsonl"

    def create(self, meta: dict[str, Any], spec_yaml: str) -> None:
        for d in (self.path, self.runs, self.configs, self.progress):
            d.mkdir(parents=True, exist_ok=True)
        self.write_spec(spec_yaml)
        self.write_meta(meta)

    def write_spec(self, spec_yaml: str) -> None:
        """The spec the sweep runs (and its report reads), replaced whole."""
        tmp = self.path / "sweep.yaml.tmp"
        tmp.write_text(spec_yaml)
        os.replace(tmp, self.path / "sweep.yaml")

    def meta(self) -> dict[str, Any]:
        p = self.path / "sweep.json"
        return json.loads(p.read_text()) if p.is_file() else {}

    def write_meta(self, meta: dict[str, Any]) -> None:
        write_json(self.path / "sweep.json", meta)

    def append(self, record: dict[str, Any]) -> None:
        """One finished point; flushed to disk before returning. A line cut short by a crash
        (no newline at its end) is ended first, so that it does not swallow this one."""
        line = json.dumps(record, sort_keys=True, default=str)
        with open(self.log_path, "a+b") as f:
            if f.tell() and (f.seek(-1, os.SEEK_END), f.read(1))[1] != b"\n":
                f.write(b"\n")
            f.write((line + "\n").encode())
            f.flush()
            os.fsync(f.fileno())

    def records(self) -> list[dict[str, Any]]:
        """The latest record of each point key, in the order the points first finished."""
        latest: dict[str, dict[str, Any]] = {}
        if self.log_path.is_file():
            for line in self.log_path.read_text().splitlines():
                try:
                    rec = json.loads(line)
                except json.JSONDecodeError:  # a line cut by a crash mid-write
                    continue
                latest[rec["key"]] = rec
        return list(latest.values())

    def completed_keys(self) -> set[str]:
        return {r["key"] for r in self.records() if r["status"] == RunState.COMPLETED}

    def write_points_table(self) -> list[dict[str, Any]]:
        """``points.parquet`` from the log: one row per point."""
        rows = [point_row(r) for r in self.records()]
        write_rows(self.path / "points.parquet", rows)
        return rows

    def write_loops_table(self) -> list[dict[str, Any]]:
        """``loops.parquet``: each completed run's per-loop rows with its swept values and seed."""
        rows: list[dict[str, Any]] = []
        for rec in self.records():
            path = self.path / rec["run_dir"] / "loops.parquet"
            if rec["status"] != RunState.COMPLETED or not path.is_file():
                continue
            head = {"key": rec["key"], **rec["values"], "seed": rec["seed"]}
            rows += [{**head, **r} for r in pq.read_table(path).to_pylist()]
        write_rows(self.path / "loops.parquet", rows)
        return rows


def point_row(rec: dict[str, Any]) -> dict[str, Any]:
    return {"key": rec["key"], **rec["values"], "seed": rec["seed"], "status": rec["status"],
            "reason": rec.get("reason"), "run_id": rec["run_id"], "run_dir": rec["run_dir"],
            "wall_s": rec.get("wall_s"), **{f"kpi.{k}": v for k, v in rec.get("kpis", {}).items()}}


def write_rows(path: Path, rows: list[dict[str, Any]]) -> None:
    """Rows with possibly different keys as one Parquet table: every column present in every row,
    integers as int64, numbers as float64 where any is fractional (a KPI can be an int in one run
    and a float in another), anything mixed with text as text."""
    columns: list[str] = []
    for r in rows:
        columns += [k for k in r if k not in columns]
    fields: list[tuple[str, pa.DataType]] = []
    casts: dict[str, type] = {}
    for c in columns:
        present = [v for r in rows if (v := r.get(c)) is not None]
        if present and all(isinstance(v, bool) for v in present):
            fields.append((c, pa.bool_()))
            casts[c] = bool
        elif present and all(isinstance(v, int) and not isinstance(v, bool) for v in present):
            fields.append((c, pa.int64()))
            casts[c] = int
        elif present and all(isinstance(v, int | float) and not isinstance(v, bool) for v in present):
            fields.append((c, pa.float64()))
            casts[c] = float
        else:
            fields.append((c, pa.string()))
            casts[c] = str
    table = [{c: (None if (v := r.get(c)) is None else casts[c](v)) for c in columns} for r in rows]
    write_table(path, table, schema=pa.schema(fields))
