"""The provisioned Grafana dashboards ask Prometheus for series that exist: the compose platform
is brought up, a smoke run goes through it in containers, and every PromQL expression of every
dashboard must return at least one series over the run (asked over Prometheus' HTTP API, so
Grafana itself need not run)."""

from __future__ import annotations

import json
import os
import secrets
import shutil
import subprocess
import time
import urllib.parse
import urllib.request
from pathlib import Path
from typing import Any

import pytest

pytestmark = pytest.mark.docker
ROOT = Path(__file__).parents[2]
DASHBOARDS = sorted((ROOT / "configs" / "grafana" / "dashboards").glob("*.json"))
PROMETHEUS = "http://127.0.0.1:9090"
API = "http://127.0.0.1:8080"


def expressions() -> list[tuple[str, str, str]]:
    out = []
    for path in DASHBOARDS:
        board = json.loads(path.read_text())
        for panel in board["panels"]:
            for target in panel["targets"]:
                out.append((path.stem, panel["title"], target["expr"]))
    return out


def test_every_dashboard_names_the_provisioned_datasource() -> None:
    ds = (ROOT / "configs" / "grafana" / "provisioning" / "datasources" / "prometheus.yaml").read_text()
    assert "uid: cosim5g-prometheus" in ds
    assert {"overview", "network", "compute", "control"} <= {p.stem for p in DASHBOARDS}
    for path in DASHBOARDS:
        for panel in json.loads(path.read_text())["panels"]:
            assert panel["datasource"]["uid"] == "cosim5g-prometheus", (path.name, panel["title"])
            assert panel["targets"], (path.name, panel["title"])


def _compose() -> list[str]:
    if subprocess.run(["docker", "compose", "version"], capture_output=True).returncode == 0:
        return ["docker", "compose"]
    exe = shutil.which("docker-compose")
    if exe is None:
        pytest.skip("no docker compose")
    return [exe]


def _get(url: str, token: str | None = None, timeout: float = 10) -> Any:
    req = urllib.request.Request(url, headers={"Authorization": f"Bearer {token}"} if token else {})
    with urllib.request.urlopen(req, timeout=timeout) as resp:
        return json.loads(resp.read().decode())


def _post(url: str, body: Any, token: str) -> Any:
    req = urllib.request.Request(url, data=json.dumps(body).encode(), method="POST",
                                 headers={"Authorization": f"Bearer {token}", "content-type": "application/json"})
    with urllib.request.urlopen(req, timeout=30) as resp:
        return json.loads(resp.read().decode())


def _ports_free() -> bool:
    import socket
    for port in (8080, 9090):
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                return False
    return True


@pytest.fixture(scope="module")
def platform(docker_client: Any, tmp_path_factory: pytest.TempPathFactory) -> Any:
    if not _ports_free():
        pytest.skip("ports 8080/9090 are taken (is the platform up? `make down`)")
    work = tmp_path_factory.mktemp("platform")
    (work / "results" / "runs").mkdir(parents=True)
    os.chown(work / "results", 10001, 10001) if os.geteuid() == 0 else None
    os.chown(work / "results" / "runs", 10001, 10001) if os.geteuid() == 0 else None
    token = secrets.token_urlsafe(32)
    env = {**os.environ, "PWD": str(work), "DOCKER_GID": str(os.stat("/var/run/docker.sock").st_gid),
           "COSIM5G_TOKEN": token, "COSIM5G_UID": "10001", "COSIM5G_GID": "10001"}
    compose = [*_compose(), "-p", "cosim5gdash", "-f", str(ROOT / "docker-compose.yml")]
    up = subprocess.run([*compose, "up", "-d"], env=env, cwd=ROOT, capture_output=True, text=True, timeout=600)
    try:
        assert up.returncode == 0, up.stderr[-3000:]
        deadline = time.monotonic() + 180
        while time.monotonic() < deadline:
            try:
                if _get(f"{API}/healthz")["status"] == "ok" and \
                        urllib.request.urlopen(f"{PROMETHEUS}/-/ready", timeout=5).status == 200:
                    break
            except OSError:
                pass
            time.sleep(1)
        yield token
    finally:
        subprocess.run([*compose, "down", "-v", "--remove-orphans"], env=env, cwd=ROOT, capture_output=True,
                       timeout=300)


def test_every_panel_query_returns_series_after_a_docker_smoke_run(platform: str) -> None:
    token = platform
    t0 = time.time()
    # A co-design policy, so that the Edge's load control (fill, cap, loops served) has series:
    # PDP 1 runs none, and a series exists only where one runs.
    run_id = _post(f"{API}/runs", {"scenario": "smoke",
                                   "overrides": ["runtime=docker", "duration_s=8", "policy.name=heuristic"]},
                   token)["run_id"]
    deadline = time.monotonic() + 900
    while time.monotonic() < deadline:
        run = _get(f"{API}/runs/{run_id}", token)
        if run["status"] not in ("pending", "running"):
            break
        time.sleep(2)
    assert run["status"] == "completed", run.get("reason")
    time.sleep(12)  # two more scrapes of the coordinator
    t1 = time.time()
    missing = []
    for board, title, expr in expressions():
        q = urllib.parse.urlencode({"query": expr, "start": t0, "end": t1, "step": 5})
        result = _get(f"{PROMETHEUS}/api/v1/query_range?{q}")
        assert result["status"] == "success", (board, title, expr, result)
        if not result["data"]["result"]:
            missing.append(f"{board} / {title}: {expr}")
    assert not missing, "panels with no series:\n" + "\n".join(missing)
