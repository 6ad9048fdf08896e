"""The REST API served by a real `cosim5g serve` process: validation, a run followed to its end,
/metrics."""

from __future__ import annotations

import subprocess
import sys
import time
from pathlib import Path

import pytest

from coordinator.client import ApiError
from coordinator.client import request as call
from coordinator.run import free_port

pytestmark = pytest.mark.integration
ROOT = Path(__file__).parents[2]


@pytest.fixture
def server(tmp_path: Path):
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "coordinator.cli", "serve", "--port", str(port),
         "--results", str(tmp_path / "runs"), "--db", str(tmp_path / "store.db"),
         "--scenarios", str(ROOT / "configs" / "scenarios")],
        cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    base = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        try:
            if call(base, "GET", "/healthz")[0] == 200:
                break
        except ApiError:
            time.sleep(0.2)
    yield base
    proc.terminate()
    proc.wait(30)


def test_api_validates_starts_and_reports_a_run(server: str) -> None:
    assert "smoke" in call(server, "GET", "/scenarios")[1]
    status, body = call(server, "POST", "/runs", {"scenario": "smoke", "overrides": ["camera.fsp=3"]})
    assert status == 422 and body["detail"][0]["field"] == "camera.fsp"
    assert call(server, "POST", "/runs", {"scenario": "nope"})[0] == 422
    assert call(server, "POST", "/runs", {"bogus": 1})[0] == 422
    status, body = call(server, "POST", "/runs", {"scenario": "smoke", "config": {"duration_s": 2}})
    assert status == 201
    run_id = body["run_id"]
    deadline = time.monotonic() + 300
    while time.monotonic() < deadline:
        run = call(server, "GET", f"/runs/{run_id}")[1]
        if run["status"] not in ("pending", "running"):
            break
        time.sleep(0.5)
    assert run["status"] == "completed", run["reason"]
    assert run["kpis"]["sim_time_s"] == 2.0 and run["config"]["duration_s"] == 2.0
    assert any(x["run_id"] == run_id for x in call(server, "GET", "/runs")[1])
    assert 'cosim_coordinator_runs_total{status="completed"} 1.0' in call(server, "GET", "/metrics")[1]
    assert call(server, "GET", "/runs/none")[0] == 404
