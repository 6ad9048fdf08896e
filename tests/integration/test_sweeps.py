"""Sweeps end to end: real `cosim5g sweep` processes running real points (tiny scenarios)."""

from __future__ import annotations

import json
import os
import re
import signal
import subprocess
import sys
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from support import MODEL_TIMING, local_ray_cluster, processes_with

from coordinator.run import free_port

pytestmark = pytest.mark.integration
ROOT = Path(__file__).parents[2]
FIGURES = ["fig4_success", "fig5_traffic", "fig6_latency_cdf"]


def write_spec(path: Path, name: str, loops: list[int]) -> Path:
    spec = {"name": name, "base": "baseline", "seeds": 1, "grid": {"loops": loops},
            "set": {"duration_s": 2.5, "detailed_loops": 0, **MODEL_TIMING},
            "figures": {"latency_loads": loops[:2]}}
    path.write_text(json.dumps(spec))  # JSON is YAML
    return path


def sweep(*args: str) -> subprocess.CompletedProcess[str]:
    return subprocess.run([sys.executable, "-m", "interfaces.cli", "sweep", *args, "--quiet"], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)


def only_dir(root: Path) -> Path:
    [d] = [p for p in root.iterdir() if p.is_dir()]
    return d



def test_killed_sweep_resumes_with_only_the_missing_points_and_reports(tmp_path: Path) -> None:
    spec = write_spec(tmp_path / "three.yaml", "three", [1, 2, 3])
    results = tmp_path / "sweeps"
    proc = subprocess.Popen([sys.executable, "-m", "interfaces.cli", "sweep", str(spec), "--results",
                             str(results), "--quiet"], cwd=ROOT, stdout=subprocess.DEVNULL,
                            stderr=subprocess.DEVNULL)
    deadline = time.monotonic() + 300
    log = None
    while time.monotonic() < deadline:
        if results.exists() and any(results.iterdir()):
            log = only_dir(results) / "points.jsonl"
            if log.is_file() and log.read_text().count("\n") >= 1:
                break
        assert proc.poll() is None, "the sweep ended before it could be killed"
        time.sleep(0.2)
    assert log is not None
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    sweep_dir = log.parent
    first = [json.loads(line) for line in log.read_text().splitlines()]
    assert len(first) == 1 and first[0]["status"] == "completed"
    # The point in flight dies with the sweep (parent-death signal), its federates with it.
    deadline = time.monotonic() + 20
    while processes_with(sweep_dir) and time.monotonic() < deadline:
        time.sleep(0.5)
    assert processes_with(sweep_dir) == []

    done = sweep(str(spec), "--resume", str(sweep_dir))
    assert done.returncode == 0, done.stderr
    lines = [json.loads(line) for line in log.read_text().splitlines()]
    assert sorted(r["values"]["loops"] for r in lines) == [1, 2, 3], "each point ran once"
    assert lines[0] == first[0], "the completed point was kept, not rerun"
    points = pq.read_table(sweep_dir / "points.parquet").to_pylist()
    assert sorted(p["loops"] for p in points) == [1, 2, 3] and len({p["key"] for p in points}) == 3
    assert all(p["status"] == "completed" and p["kpi.tasks"] >= 0 for p in points)
    summary = pq.read_table(sweep_dir / "summary.parquet").to_pylist()
    assert [r["loops"] for r in summary] == [1, 2, 3]
    loops = pq.read_table(sweep_dir / "loops.parquet").to_pylist()
    assert len(loops) == 1 + 2 + 3 and {r["loop"] for r in loops if r["loops"] == 3} == {0, 1, 2}
    assert all(r["ul_packets"] > 0 and r["mean_pdp"] == 1.0 for r in loops)
    cap = json.loads((sweep_dir / "capacity.json").read_text())
    assert cap["series"]["all"]["success>=100%"]["capacity"] in (0, 1, 2, 3)
    assert cap["radio_cell_ul_capacity_mbps"] > 100
    for stem in FIGURES:
        for ext in ("png", "svg"):
            assert (sweep_dir / f"{stem}.{ext}").stat().st_size > 1000
    report = (sweep_dir / "report.md").read_text()
    assert "## Capacity" in report and "fig4_success.png" in report

    # The report is rebuilt from the records alone.
    for stem in FIGURES:
        (sweep_dir / f"{stem}.png").unlink()
    (sweep_dir / "report.md").unlink()
    rebuilt = subprocess.run([sys.executable, "-m", "interfaces.cli", "report", str(sweep_dir)], cwd=ROOT,
                             capture_output=True, text=True, timeout=120)
    assert rebuilt.returncode == 0, rebuilt.stderr
    assert (sweep_dir / "report.md").read_text() == report
    assert all((sweep_dir / f"{stem}.png").is_file() for stem in FIGURES)


@pytest.fixture
def ray_cluster():  # type: ignore[no-untyped-def]
    pytest.importorskip("ray")
    with local_ray_cluster(free_port(), 1) as address:
        yield address


def test_ray_executor_gives_the_same_kpis_as_the_local_one(tmp_path: Path, ray_cluster: str) -> None:
    spec = write_spec(tmp_path / "two.yaml", "two", [1, 2])
    on_ray = sweep(str(spec), "--executor", "ray", "--address", ray_cluster, "--results", str(tmp_path / "ray"))
    assert on_ray.returncode == 0, on_ray.stderr
    local = sweep(str(spec), "--results", str(tmp_path / "local"))
    assert local.returncode == 0, local.stderr

    def kpis(root: Path) -> dict[int, tuple]:
        rows = pq.read_table(only_dir(root) / "points.parquet").to_pylist()
        return {r["loops"]: (r["key"], r["status"], r["kpi.trace_hash"], r["kpi.tasks"], r["kpi.tasks_placed"],
                             r["kpi.ul_packets"], r["kpi.ul_ip_latency_ms.p99"]) for r in rows}

    assert kpis(tmp_path / "ray") == kpis(tmp_path / "local")
    assert all(k[2] for k in kpis(tmp_path / "ray").values()), "completed runs carry their trace hash"
    ray_dir = only_dir(tmp_path / "ray")
    for rec in (json.loads(line) for line in (ray_dir / "points.jsonl").read_text().splitlines()):
        assert (ray_dir / rec["run_dir"] / "packets.parquet").is_file(), "the run directory came back"


def test_a_point_whose_ray_node_is_lost_goes_back_to_the_queue_once(tmp_path: Path) -> None:
    ray = pytest.importorskip("ray")
    spec = write_spec(tmp_path / "two.yaml", "two", [1, 2])
    # Points long enough for the node to be lost while they run.
    spec.write_text(spec.read_text().replace('"duration_s": 2.5', '"duration_s": 30'))
    results = tmp_path / "sweeps"
    # A cluster of its own: the node lost here does not come back.
    with local_ray_cluster(free_port(), 1) as address:
        ray.init(address=address, log_to_driver=False)
        try:
            [worker] = [n["NodeID"] for n in ray.nodes() if "node:__internal_head__" not in n["Resources"]]
        finally:
            ray.shutdown()
        proc = subprocess.Popen([sys.executable, "-m", "interfaces.cli", "sweep", str(spec), "--executor", "ray",
                                 "--address", address, "--results", str(results), "--quiet"], cwd=ROOT,
                                stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True)
        # Both points running (one a node, one CPU each): the worker node's raylet dies. A point
        # is told by its folder (its run's processes all name it).
        deadline = time.monotonic() + 300
        while len(running_points()) < 2:
            assert proc.poll() is None and time.monotonic() < deadline, "the points did not both start"
            time.sleep(0.2)
        time.sleep(1.0)
        raylets = [pid for pid in processes_with(f"--node_id={worker}")
                   if "raylet" in Path(f"/proc/{pid}/cmdline").read_text()]
        assert raylets
        for pid in raylets:
            os.kill(pid, signal.SIGKILL)
        _, err = proc.communicate(timeout=600)
    assert proc.returncode == 0, err
    assert "back to the queue once" in err, err
    rows = pq.read_table(only_dir(results) / "points.parquet").to_pylist()
    assert sorted((r["loops"], r["status"]) for r in rows) == [(1, "completed"), (2, "completed")]


def running_points() -> set[str]:
    """The Ray sweep points running on this host: their folders (``cosim5g-point-*``)."""
    found = set()
    for pid in processes_with("cosim5g-point-"):
        try:
            args = Path(f"/proc/{pid}/cmdline").read_bytes().split(b"\0")
        except OSError:
            continue
        found |= {m.decode() for a in args for m in re.findall(rb"cosim5g-point-[^/]+", a)}
    return found
