"""The REST API served by a real `cosim5g serve` process: validation, a run followed to its end,
/metrics; the token it writes at its first start, which clients must send."""

from __future__ import annotations

import os
import stat
import subprocess
import sys
import time
from pathlib import Path

import pytest

from coordinator.run import free_port
from interfaces.client import ApiError
from interfaces.client import request as call

pytestmark = pytest.mark.integration
ROOT = Path(__file__).parents[2]


@pytest.fixture
def token_file(tmp_path: Path) -> Path:
    return tmp_path / "auth" / "api-token"


@pytest.fixture
def server(tmp_path: Path, token_file: Path, monkeypatch: pytest.MonkeyPatch):
    """A coordinator with no token given: it writes one to ``token_file``, which clients then use."""
    monkeypatch.delenv("COSIM5G_TOKEN", raising=False)
    port = free_port()
    proc = subprocess.Popen(
        [sys.executable, "-m", "interfaces.cli", "serve", "--port", str(port),
         "--results", str(tmp_path / "runs"), "--db", str(tmp_path / "store.db"),
         "--scenarios", str(ROOT / "configs" / "scenarios"), "--token-file", str(token_file)],
        cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL, env=dict(os.environ))
    base = f"http://127.0.0.1:{port}"
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        try:
            if call(base, "GET", "/healthz")[0] == 200:
                break
        except ApiError:
            time.sleep(0.2)
    monkeypatch.setenv("COSIM5G_TOKEN_FILE", str(token_file))  # what interfaces.client reads
    yield base
    proc.terminate()
    proc.wait(30)


def test_the_token_is_written_at_first_start_and_required(server: str, token_file: Path) -> None:
    assert stat.S_IMODE(token_file.stat().st_mode) == 0o600
    assert call(server, "GET", "/healthz", token="")[0] == 200
    status, body = call(server, "GET", "/runs", token="")
    assert status == 401 and "Authorization: Bearer" in body["detail"] and str(token_file) in body["detail"]
    assert call(server, "GET", "/runs", token="not-the-token-0123456789")[0] == 401
    assert call(server, "GET", "/runs")[0] == 200  # the token from COSIM5G_TOKEN_FILE

    def submit(*extra: str, env: dict[str, str]) -> subprocess.CompletedProcess[str]:
        return subprocess.run([sys.executable, "-m", "interfaces.cli", "submit", "nope", "--api", server,
                               "--wait-s", "10", *extra], cwd=ROOT, capture_output=True, text=True,
                              env=env, timeout=60)

    bare = {k: v for k, v in os.environ.items() if not k.startswith("COSIM5G_TOKEN")}
    refused = submit("--token-file", str(token_file.parent / "missing"), env=bare)
    assert refused.returncode == 2
    assert "HTTP 401" in refused.stderr and "COSIM5G_TOKEN" in refused.stderr and "--token-file" in refused.stderr
    # With the token the request gets through, to be refused for what it asks: no such scenario.
    accepted = submit("--token-file", str(token_file), env=bare)
    assert accepted.returncode == 2 and "HTTP 422" in accepted.stderr and "'nope' is not one of" in accepted.stderr


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
