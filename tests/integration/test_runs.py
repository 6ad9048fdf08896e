"""End-to-end runs in the process runtime: real federate processes over a real zenoh router."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pyarrow.parquet as pq
import pytest
from support import MODEL_TIMING_SETS, processes_with

from coordinator.conductor import Progress
from coordinator.run import execute_run
from coordinator.runtime_process import ProcessLauncher
from scenario.schema import load_scenario

pytestmark = pytest.mark.integration
ROOT = Path(__file__).parents[2]
SMOKE = ROOT / "configs" / "scenarios" / "smoke.yaml"



def test_smoke_run_completes_with_both_loops_working(tmp_path: Path) -> None:
    proc = subprocess.run(
        [sys.executable, "-m", "interfaces.cli", "run", str(SMOKE), "--json", "--quiet",
         "--results", str(tmp_path)],
        capture_output=True, text=True, timeout=600, cwd=ROOT,
    )
    assert proc.returncode == 0, proc.stderr[-3000:]
    kpis = json.loads(proc.stdout.strip().splitlines()[-1])
    for key in ("status", "loops", "tasks", "task_success_rate", "ul_injected_mbps", "ul_throughput_mbps",
                "ip_latency_ms", "sim_time_s", "wall_time_s", "trace_hash", "results_dir"):
        assert key in kpis, key
    assert kpis["status"] == "completed" and kpis["loops"] == 2
    assert kpis["loops_with_tasks"] == 2 and kpis["tasks"] >= 4
    assert kpis["ul_packets"] > 0 and kpis["dl_packets"] > 0
    assert kpis["ul_throughput_mbps"] > 0 and kpis["ip_latency_ms"]["p99"] is not None
    assert kpis["estimator"] == "learned" and kpis["camera_bitrate_mbps_mean"] > 0
    assert kpis["federates"]["edge"]["estimator_fallback_reason"] == ""
    run_dir = Path(kpis["results_dir"])
    for name in ("config.yaml", "versions.json", "kpis.json", "tasks.parquet", "packets.parquet",
                 "jobs.parquet", "frames.parquet", "frames/camera-0.png"):
        assert (run_dir / name).exists(), name
    assert not processes_with(kpis["run_id"])


def test_a_metrics_port_set_for_the_coordinator_does_not_fail_its_process_federates(tmp_path: Path) -> None:
    # Every federate of the process runtime shares the host: the port is the docker runtime's
    # (a port per container); here it must not be handed to every federate, which would fail
    # all but the first to bind it.
    from coordinator.run import free_port

    env = {**os.environ, "COSIM5G_METRICS_PORT": str(free_port())}
    proc = subprocess.run(
        [sys.executable, "-m", "interfaces.cli", "run", str(SMOKE), "--json", "--quiet", "--results",
         str(tmp_path), "--set", "duration_s=0.5"], capture_output=True, text=True, timeout=600, cwd=ROOT, env=env)
    assert proc.returncode == 0, proc.stderr[-3000:]
    kpis = json.loads(proc.stdout.strip().splitlines()[-1])
    assert kpis["status"] == "completed"
    logs = "".join(p.read_text() for p in (Path(kpis["results_dir"]) / "logs").glob("*.log"))
    assert "metrics not served" not in logs


def run_trace(tmp_path: Path, seed: int) -> str:
    sc = load_scenario(SMOKE, ["duration_s=3", f"seed={seed}", *MODEL_TIMING_SETS])
    result = execute_run(sc, tmp_path)
    assert result.status == "completed", result.reason
    return str(result.kpis["trace_hash"])


def test_same_seed_and_model_timing_give_the_same_trace(tmp_path: Path) -> None:
    first = run_trace(tmp_path, 11)
    assert run_trace(tmp_path, 11) == first
    assert run_trace(tmp_path, 12) != first


@pytest.mark.parametrize("detailed", [0, 1])
def test_the_core_group_simulates_what_separate_processes_do(tmp_path: Path, detailed: int) -> None:
    """Physics, netsim and the abstract loops served as one group (with long windows when no loop
    is detailed) decide every packet and task exactly as when each has a process of its own,
    up to the run's end, which no window is aligned to here."""
    tables = {}
    for cohost in ("core", "none"):
        sc = load_scenario(ROOT / "configs" / "scenarios" / "baseline.yaml",
                           ["loops=4", f"detailed_loops={detailed}", "duration_s=2.9195", f"cohost={cohost}",
                            *MODEL_TIMING_SETS])
        result = execute_run(sc, tmp_path / cohost)
        assert result.status == "completed", result.reason
        if detailed == 0:
            assert result.kpis["windows"] < 100 if cohost == "core" else result.kpis["windows"] > 2000
        tables[cohost] = {name: pq.read_table(result.run_dir / f"{name}.parquet").sort_by(keys).to_pylist()
                          for name, keys in (("packets", "packet_id"),
                                            ("tasks", [("work_cell", "ascending"), ("task_id", "ascending")]))}
    assert tables["core"] == tables["none"]
    assert len(tables["core"]["packets"]) > 1000
    assert max(t["end_us"] for t in tables["core"]["tasks"]) <= 2_919_500


def _run_with_fault(tmp_path: Path, victim: str, fault: signal.Signals, overrides: list[str]):
    sc = load_scenario(SMOKE, ["duration_s=20", *overrides])
    launcher = ProcessLauncher()
    struck: dict[str, float] = {}

    def on_progress(p: Progress) -> None:
        if p.t_us > 500_000 and not struck:
            os.kill(launcher.procs[victim].pid, fault)
            struck["at"] = time.monotonic()

    result = execute_run(sc, tmp_path, launcher=launcher, on_progress=on_progress)
    return result, time.monotonic() - struck["at"]


@pytest.mark.parametrize("victim,overrides", [("core", []), ("netsim", ["cohost=none"]), ("edge", []),
                                              ("camera-1", []), ("robot-0", [])])
def test_killing_a_federate_fails_the_run_quickly_naming_it(tmp_path: Path, victim: str,
                                                            overrides: list[str]) -> None:
    result, elapsed = _run_with_fault(tmp_path, victim, signal.SIGKILL, overrides)
    assert result.status == "failed"
    assert result.kpis["failed_federate"] == victim and victim in (result.reason or "")
    assert elapsed < 15
    assert not processes_with(result.run_id)


def test_a_hung_federate_fails_the_run_after_the_window_timeout(tmp_path: Path) -> None:
    result, elapsed = _run_with_fault(tmp_path, "edge", signal.SIGSTOP, ["watchdog.window_timeout_s=3"])
    assert result.status == "failed" and "edge" in (result.reason or "") and "hung" in (result.reason or "")
    assert elapsed < 15
    assert not processes_with(result.run_id)


def test_cancel_ends_the_run_as_cancelled(tmp_path: Path) -> None:
    sc = load_scenario(SMOKE, ["duration_s=20"])
    cancel = threading.Event()

    def on_progress(p: Progress) -> None:
        if p.t_us > 300_000:
            cancel.set()

    result = execute_run(sc, tmp_path, on_progress=on_progress, cancel=cancel)
    assert result.status == "cancelled"
    assert (result.run_dir / "kpis.json").exists()
    assert not processes_with(result.run_id)
