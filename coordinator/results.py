"""Run results: merge the federates' tables and compute the KPIs of a run directory.

Layout of a run directory: ``config.yaml`` (resolved scenario), ``versions.json``, ``kpis.json``,
``tasks.parquet`` (per task), ``packets.parquet`` (per IP packet), ``jobs.parquet`` (per compute
job), ``frames.parquet`` (per camera frame), ``logs/`` and ``frames/`` (PNG snapshots).
"""

from __future__ import annotations

import platform
import subprocess
from collections import Counter
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np

from services.common.tables import read_rows, write_table


def versions() -> dict[str, str]:
    out = {"python": platform.python_version()}
    for dist in ("cosim5g", "eclipse-zenoh", "mujoco", "numpy", "opencv-python-headless", "pydantic"):
        try:
            out[dist] = metadata.version(dist)
        except metadata.PackageNotFoundError:
            out[dist] = "absent"
    try:
        commit = subprocess.run(["git", "rev-parse", "--short", "HEAD"], capture_output=True, text=True,
                                timeout=5, cwd=Path(__file__).parent)
        if commit.returncode == 0:
            out["git"] = commit.stdout.strip()
    except (OSError, subprocess.SubprocessError):
        pass
    return out


def merge_tables(run_dir: Path, prefix: str) -> list[dict[str, Any]]:
    """Concatenate ``tables/<prefix>-*.parquet`` into ``<prefix>.parquet``."""
    rows: list[dict[str, Any]] = []
    for path in sorted((run_dir / "tables").glob(f"{prefix}-*.parquet")):
        part = read_rows(path)
        keys = sorted({k for r in part for k in r})
        rows.extend({k: r.get(k) for k in keys} for r in part)
    if rows:
        columns = sorted({k for r in rows for k in r})
        write_table(run_dir / f"{prefix}.parquet", [{k: r.get(k) for k in columns} for r in rows])
    return rows


def _pct(values: list[float], q: float) -> float | None:
    return float(np.percentile(values, q)) if values else None


def compute_kpis(run_dir: Path, sim_time_s: float, loops: int) -> dict[str, Any]:
    """KPIs from the tables of a finished run."""
    tasks = [t for t in read_rows(run_dir / "tasks.parquet") if t["outcome"] != "unfinished"]
    packets = read_rows(run_dir / "packets.parquet")
    jobs = merge_tables(run_dir, "jobs")
    merge_tables(run_dir, "frames")
    sim = max(sim_time_s, 1e-9)
    ul = [p for p in packets if p["dir"] == "ul"]
    dl = [p for p in packets if p["dir"] == "dl"]
    delivered = [p for p in packets if p["deliver_us"] is not None]
    lat_ms = [p["latency_us"] / 1000 for p in delivered]
    per_loop_bytes: Counter[str] = Counter()
    for p in ul:
        per_loop_bytes[p["ue"]] += p["size_bytes"]
    camera_mbps = {ue: b * 8 / sim / 1e6 for ue, b in sorted(per_loop_bytes.items())}
    placed = sum(1 for t in tasks if t["success"])
    by_cell: Counter[int] = Counter(t["cell"] for t in tasks)
    node_latency: dict[str, dict[str, float | None]] = {}
    for kind in sorted({(j["node"].split("-")[0], j["kind"]) for j in jobs}):
        d = [j["duration_us"] / 1000 for j in jobs if (j["node"].split("-")[0], j["kind"]) == kind]
        qd = [j["queue_us"] / 1000 for j in jobs if (j["node"].split("-")[0], j["kind"]) == kind]
        node_latency[f"{kind[0]}/{kind[1]}"] = {"p50_ms": _pct(d, 50), "p99_ms": _pct(d, 99),
                                                "queue_p99_ms": _pct(qd, 99), "jobs": len(d)}
    return {
        "loops": loops,
        "tasks": len(tasks),
        "tasks_placed": placed,
        "task_success_rate": placed / len(tasks) if tasks else None,
        "loops_with_tasks": len(by_cell),
        "task_outcomes": dict(Counter(t["outcome"] for t in tasks)),
        "ul_packets": len(ul),
        "dl_packets": len(dl),
        "ul_injected_mbps": sum(p["size_bytes"] for p in ul) * 8 / sim / 1e6,
        "ul_throughput_mbps": sum(p["size_bytes"] for p in ul if p["deliver_us"] is not None) * 8 / sim / 1e6,
        "dl_throughput_mbps": sum(p["size_bytes"] for p in dl if p["deliver_us"] is not None) * 8 / sim / 1e6,
        "ip_latency_ms": {"p50": _pct(lat_ms, 50), "p99": _pct(lat_ms, 99), "max": max(lat_ms, default=None)},
        "ul_ip_latency_ms": {"p50": _pct([p["latency_us"] / 1000 for p in ul if p["deliver_us"] is not None], 50),
                             "p99": _pct([p["latency_us"] / 1000 for p in ul if p["deliver_us"] is not None], 99)},
        "lost_packets": dict(Counter(p["lost_cause"] for p in packets if p["deliver_us"] is None)),
        "camera_bitrate_mbps": camera_mbps,
        "camera_bitrate_mbps_mean": float(np.mean(list(camera_mbps.values()))) if camera_mbps else 0.0,
        "compute_latency": node_latency,
    }
