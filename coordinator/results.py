"""Run results: merge the federates' tables and compute the KPIs of a run directory.

The layout of a run directory and its KPIs: docs/architecture.md sec. 9; ``merge_tables`` merges
the streamed tables of completed and failed runs alike.
"""

from __future__ import annotations

import hashlib
import platform
import subprocess
from collections import Counter
from importlib import metadata
from pathlib import Path
from typing import Any

import numpy as np
import pyarrow as pa
import pyarrow.compute as pc
import pyarrow.parquet as pq
import yaml

from fabric.tables import TABLES, merge_parts, read_rows, write_table


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


def merge_tables(run_dir: Path) -> dict[str, dict[str, Any]]:
    """Merge the federates' streamed parts of every run table (``tasks``, ``packets``, ``jobs``,
    ``frames``) into ``<table>.parquet``; a table nobody wrote to is written empty, with its
    columns. Per table: rows merged and, per federate, rows, simulated time recorded up to and
    whether the federate closed its part (``fabric.tables.merge_parts``). Merging again
    keeps what was merged."""
    return {name: merge_parts(run_dir, name) for name in TABLES}


def recorded_summary(merged: dict[str, dict[str, Any]]) -> dict[str, Any]:
    """How far the records of a run go, for ``kpis.json``: rows per table, and per part (a list,
    so that sweep records, which flatten dicts, skip it) the federate's rows and reach."""
    parts = [{"table": table, "federate": fed, **info}
             for table, m in merged.items() for fed, info in sorted(m["parts"].items())]
    return {"rows": {table: m["rows"] for table, m in merged.items()}, "parts": parts}


# What the simulated entities did: every task's life, every packet's fate, every transmission and
# handover. Their rows, sorted, do not depend on which process wrote them.
OUTCOME_TABLES = ("tasks", "packets", "transmissions", "handovers")


def results_hash(run_dir: Path) -> str:
    """One hash over the merged outcome tables of a run (``OUTCOME_TABLES``), each sorted by all
    its columns: the same for the same outcomes whatever the processes, partitions or windows
    that produced them (``trace_hash`` also covers those)."""
    h = hashlib.sha256()
    for name in OUTCOME_TABLES:
        path = run_dir / f"{name}.parquet"
        table = pq.read_table(path) if path.exists() else TABLES[name].empty_table()
        table = table.sort_by([(c, "ascending") for c in table.column_names]).combine_chunks()
        h.update(f"{name}:{table.num_rows};".encode())
        for column in table.column_names:
            col = table[column]
            h.update(column.encode())
            h.update(np.asarray(pc.is_null(col)).tobytes())
            if pa.types.is_string(col.type):
                # Indices into the values in order of appearance: canonical once the rows are.
                coded = pc.dictionary_encode(col).combine_chunks()
                h.update("\x00".join(str(v) for v in coded.dictionary.to_pylist()).encode())
                col = coded.indices
            filled = pc.fill_null(col, pa.scalar(0, col.type) if not pa.types.is_boolean(col.type) else False)
            h.update(np.asarray(filled).tobytes())
    return h.hexdigest()


def _pct(values: np.ndarray, q: float) -> float | None:
    return float(np.percentile(values, q)) if len(values) else None


def compute_kpis(run_dir: Path, sim_time_s: float, loops: int) -> dict[str, Any]:
    """KPIs from the tables of a finished run. The packet and job tables are computed on as Arrow
    columns: a long run has millions of packets, and a Python object per row or per string would
    cost the coordinator GBs (a 32-loop, 300 s run has 7 million)."""
    merge_tables(run_dir)  # keeps the merged tables when the run merged them already
    tasks = [t for t in read_rows(run_dir / "tasks.parquet") if t["outcome"] != "unfinished"]
    sim = max(sim_time_s, 1e-9)
    pk = _read(run_dir / "packets.parquet", ["dir", "ue", "size_bytes", "deliver_us", "latency_us", "lost_cause"])
    is_ul, is_dl = pc.equal(pk["dir"], "ul"), pc.equal(pk["dir"], "dl")
    delivered = pc.is_valid(pk["deliver_us"])
    size = pk["size_bytes"]

    def total_bytes(mask: Any) -> int:
        return int(pc.sum(pc.filter(size, mask)).as_py() or 0)

    latency_ms = _as_ms(pc.filter(pk["latency_us"], delivered))
    ul_latency_ms = _as_ms(pc.filter(pk["latency_us"], pc.and_(delivered, is_ul)))
    per_ue = pk.filter(is_ul).group_by("ue").aggregate([("size_bytes", "sum")]).to_pydict()
    # The loops' cameras only: moving radios (AGVs) load the cell but are no camera.
    camera_mbps = {ue: b * 8 / sim / 1e6
                   for ue, b in sorted(zip(per_ue["ue"], per_ue["size_bytes_sum"], strict=True))
                   if ue.startswith("camera-")}
    lost_counts = pc.value_counts(pc.filter(pk["lost_cause"], pc.invert(delivered))).to_pylist()
    placed = sum(1 for t in tasks if t["success"])
    by_cell: Counter[int] = Counter(t["work_cell"] for t in tasks)
    jb = _read(run_dir / "jobs.parquet", ["node", "kind", "timing", "duration_us", "queue_us"])
    role = pc.replace_substring_regex(jb["node"], pattern="-.*$", replacement="")
    # Per timing too: the abstract loops' model-timed jobs must not hide the detailed loops'
    # measured ones of the same kind.
    groups = pa.table({"role": role, "kind": jb["kind"], "timing": jb["timing"]})
    keys = groups.group_by(["role", "kind", "timing"]).aggregate([]).to_pydict()
    node_latency: dict[str, dict[str, float | None]] = {}
    for r, k, t in sorted(zip(keys["role"], keys["kind"], keys["timing"], strict=True)):
        mine = pc.and_(pc.and_(pc.equal(role, r), pc.equal(jb["kind"], k)), pc.equal(jb["timing"], t))
        d = _as_ms(pc.filter(jb["duration_us"], mine))
        qd = _as_ms(pc.filter(jb["queue_us"], mine))
        node_latency[f"{r}/{k}/{t}"] = {"p50_ms": _pct(d, 50), "p99_ms": _pct(d, 99),
                                        "queue_p99_ms": _pct(qd, 99), "jobs": int(d.size)}
    return {
        "loops": loops,
        "tasks": len(tasks),
        "tasks_placed": placed,
        "task_success_rate": placed / len(tasks) if tasks else None,
        "loops_with_tasks": len(by_cell),
        "task_outcomes": dict(Counter(t["outcome"] for t in tasks)),
        "ul_packets": int(pc.sum(is_ul).as_py() or 0),
        "dl_packets": int(pc.sum(is_dl).as_py() or 0),
        "ul_injected_mbps": total_bytes(is_ul) * 8 / sim / 1e6,
        "ul_throughput_mbps": total_bytes(pc.and_(is_ul, delivered)) * 8 / sim / 1e6,
        "dl_throughput_mbps": total_bytes(pc.and_(is_dl, delivered)) * 8 / sim / 1e6,
        "ip_latency_ms": {"p50": _pct(latency_ms, 50), "p99": _pct(latency_ms, 99),
                          "max": float(latency_ms.max()) if latency_ms.size else None},
        "ul_ip_latency_ms": {"p50": _pct(ul_latency_ms, 50), "p99": _pct(ul_latency_ms, 99)},
        "lost_packets": {c["values"]: c["counts"] for c in lost_counts},
        "camera_bitrate_mbps": camera_mbps,
        "camera_bitrate_mbps_mean": float(np.mean(list(camera_mbps.values()))) if camera_mbps else 0.0,
        "compute_latency": node_latency,
        **_gnb_kpis(run_dir, pk, sim),
    }


def _gnb_kpis(run_dir: Path, pk: pa.Table, sim_s: float) -> dict[str, Any]:
    """With several gNBs (``hall.inf_layout``): per gNB ``gnb<i>.<link>.prb_utilisation`` (PRBs
    that carried a transmission over the cell's PRB-slots) and ``gnb<i>.<link>.throughput_mbps``
    (IP bytes delivered), and the distribution of the transmissions' effective SINR per link
    (``<link>_sinr_db``: p5, p50, p95). Nothing with one gNB (its tables have no gNB)."""
    packets = run_dir / "packets.parquet"
    if packets.exists() and "gnb" not in pq.read_schema(packets).names:
        return {}  # recorded before the column was
    gnb = _read(packets, ["gnb"])["gnb"]
    tx = _read(run_dir / "transmissions.parquet", ["gnb", "dir", "n_prb", "cell_prb", "sinr_db"])
    if not tx.num_rows and gnb.null_count == len(gnb):
        return {}
    out: dict[str, Any] = {}
    slots = sim_s * 1e6 / _slot_us(run_dir)
    used = tx.group_by(["gnb", "dir"]).aggregate([("n_prb", "sum"), ("cell_prb", "max")]).to_pydict()
    for g, link, prb, cell_prb in sorted(zip(used["gnb"], used["dir"], used["n_prb_sum"],
                                             used["cell_prb_max"], strict=True)):
        out[f"gnb{g}.{link}.prb_utilisation"] = prb / (cell_prb * slots) if slots else None
    sent = pa.table({"gnb": gnb, "dir": pk["dir"], "size_bytes": pk["size_bytes"]}).filter(
        pc.and_(pc.is_valid(pk["deliver_us"]), pc.is_valid(gnb)))
    delivered = sent.group_by(["gnb", "dir"]).aggregate([("size_bytes", "sum")]).to_pydict()
    for g, link, size in sorted(zip(delivered["gnb"], delivered["dir"], delivered["size_bytes_sum"],
                                    strict=True)):
        out[f"gnb{g}.{link}.throughput_mbps"] = size * 8 / sim_s / 1e6
    for link in ("ul", "dl"):
        sinr = np.asarray(pc.filter(tx["sinr_db"], pc.equal(tx["dir"], link)).to_numpy(), dtype=float)
        out[f"{link}_sinr_db"] = {f"p{q}": _pct(sinr, q) for q in (5, 50, 95)}
    return out


def _slot_us(run_dir: Path) -> int:
    """The run's NR slot, us (``netsim.slot_us`` of its resolved scenario; 1000 without one)."""
    try:
        config = yaml.safe_load((run_dir / "config.yaml").read_text())
        return int(config["netsim"]["slot_us"])
    except (OSError, KeyError, TypeError, ValueError, yaml.YAMLError):
        return 1000


def _read(path: Path, names: list[str]) -> pa.Table:
    """The ``names`` columns of a merged run table (an empty table with them when it has none)."""
    schema = TABLES[path.stem]
    if path.exists():
        return pq.read_table(path, columns=names)
    return pa.table({n: pa.array([], type=schema.field(n).type) for n in names})


def _as_ms(values: Any) -> np.ndarray:
    """Microseconds (an Arrow array without nulls) as a numpy array of milliseconds."""
    return np.asarray(values.to_numpy(), dtype=np.float64) / 1000


def _column(path: Path, names: list[str]) -> dict[str, np.ndarray] | None:
    """Columns of a Parquet table as numpy arrays (None where the file is absent or lacks one)."""
    if not path.exists():
        return None
    table = pq.read_table(path)
    if not set(names) <= set(table.column_names):
        return None
    return {n: table.column(n).to_numpy(zero_copy_only=False) for n in names}


def _percentiles_ms(lat_us: np.ndarray) -> tuple[float | None, float | None]:
    if lat_us.size == 0:
        return None, None
    p50, p99 = np.percentile(lat_us, [50, 99]) / 1000
    return float(p50), float(p99)


def loop_kpis(run_dir: Path, loops: int, detailed_loops: int, sim_time_s: float) -> list[dict[str, Any]]:
    """Per-loop KPIs of a run, written to ``loops.parquet``: one row per control loop.

    A knee in a sweep's success curve is traced back to loops with these: each loop's tasks and
    their failure causes, the PDP its camera ran at, its uplink traffic, latency and losses.
    """
    sim = max(sim_time_s, 1e-9)
    rows: list[dict[str, Any]] = [{"loop": i, "detailed": i < detailed_loops} for i in range(loops)]
    tasks = _column(run_dir / "tasks.parquet", ["work_cell", "outcome", "reason"])
    for r in rows:
        r.update(tasks=0, placed=0, missed=0, dropped=0, failure_causes="")
    if tasks is not None:
        for i, r in enumerate(rows):
            mine = tasks["work_cell"] == i
            outcome = tasks["outcome"][mine]
            reason = tasks["reason"][mine]
            ended = outcome != "unfinished"
            failed = ended & (outcome != "placed")
            causes = Counter(f"{o}: {c}" if c else str(o) for o, c in zip(outcome[failed], reason[failed],
                                                                        strict=True))
            r.update(tasks=int(ended.sum()), placed=int((outcome == "placed").sum()),
                     missed=int((outcome == "missed").sum()), dropped=int((outcome == "dropped").sum()),
                     failure_causes="; ".join(f"{k} x{n}" for k, n in sorted(causes.items())))
    for r in rows:
        r["success_rate"] = r["placed"] / r["tasks"] if r["tasks"] else None

    # PDP: the detailed cameras record it per frame; the abstract loops record frames and how many
    # they kept, whose ratio is the mean PDP they ran at (each frame is kept with probability PDP).
    for r in rows:
        r.update(frames=0, frames_kept=0, mean_pdp=None)
    frames = _column(run_dir / "frames.parquet", ["loop", "pdp", "kept"])
    if frames is not None:
        camera = ~np.isnan(frames["pdp"].astype(float))
        for r in rows:
            mine = camera & (frames["loop"] == r["loop"])
            if mine.any():
                r.update(frames=int(mine.sum()), frames_kept=int(frames["kept"][mine].astype(bool).sum()),
                         mean_pdp=float(frames["pdp"][mine].astype(float).mean()))
    abstract = _column(run_dir / "tables" / "abstract-loops.parquet", ["loop", "frames", "frames_kept"])
    if abstract is not None:
        for loop, n, kept in zip(abstract["loop"], abstract["frames"], abstract["frames_kept"], strict=True):
            if 0 <= loop < loops and n:
                rows[int(loop)].update(frames=int(n), frames_kept=int(kept), mean_pdp=float(kept) / float(n))

    # Packets as Arrow columns, the UE names dictionary-encoded: millions of rows, a few dozen UEs.
    pk = _read(run_dir / "packets.parquet", ["ue", "dir", "size_bytes", "latency_us", "lost_cause"])
    for r in rows:
        r.update(ul_packets=0, ul_injected_mbps=0.0, ul_throughput_mbps=0.0, ul_latency_p50_ms=None,
                 ul_latency_p99_ms=None, dl_latency_p50_ms=None, dl_latency_p99_ms=None, lost_packets=0,
                 lost_causes="")
    if pk.num_rows:
        # Each loop has two radio endpoints: camera-i (uplink video, downlink QoS) and robot-i.
        ues = pc.dictionary_encode(pk["ue"]).combine_chunks()
        loop_of_ue = np.array([int(u.rsplit("-", 1)[1]) for u in ues.dictionary.to_pylist()], dtype=np.int64)
        loop_of = loop_of_ue[ues.indices.to_numpy()]
        lat = np.asarray(pk["latency_us"].to_numpy(), dtype=np.float64)  # NaN: not delivered
        delivered = ~np.isnan(lat)
        ul = pc.equal(pk["dir"], "ul").to_numpy()
        size = np.asarray(pk["size_bytes"].to_numpy(), dtype=np.int64)
        lost_rows = ~delivered
        causes_by_loop: dict[int, Counter[str]] = {}
        if lost_rows.any():
            lost = pa.table({"loop": loop_of[lost_rows],
                             "cause": pc.filter(pk["lost_cause"], pa.array(lost_rows))})
            counted = lost.group_by(["loop", "cause"]).aggregate([("loop", "count")]).to_pydict()
            for loop, cause, n in zip(counted["loop"], counted["cause"], counted["loop_count"], strict=True):
                causes_by_loop.setdefault(int(loop), Counter())[str(cause)] += int(n)
        for r in rows:
            mine = loop_of == r["loop"]
            mul, mdl = mine & ul, mine & ~ul
            ul_p50, ul_p99 = _percentiles_ms(lat[mul & delivered])
            dl_p50, dl_p99 = _percentiles_ms(lat[mdl & delivered])
            causes = causes_by_loop.get(r["loop"], Counter())
            r.update(ul_packets=int(mul.sum()), ul_injected_mbps=float(size[mul].sum()) * 8 / sim / 1e6,
                     ul_throughput_mbps=float(size[mul & delivered].sum()) * 8 / sim / 1e6,
                     ul_latency_p50_ms=ul_p50, ul_latency_p99_ms=ul_p99, dl_latency_p50_ms=dl_p50,
                     dl_latency_p99_ms=dl_p99, lost_packets=int((mine & lost_rows).sum()),
                     lost_causes="; ".join(f"{k} x{n}" for k, n in sorted(causes.items())))
    write_table(run_dir / "loops.parquet", rows)
    return rows
