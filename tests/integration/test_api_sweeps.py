"""Sweeps through the REST API of a real `cosim5g serve` process: started, followed to their end,
reported, shown on the results page in a real browser, and resumed after the coordinator died."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from support import MODEL_TIMING, processes_with

from coordinator.run import free_port
from interfaces.client import ApiError
from interfaces.client import request as call

pytestmark = pytest.mark.integration
ROOT = Path(__file__).parents[2]


def tiny_spec(name: str, loops: list[int], duration_s: float = 5.0) -> dict[str, Any]:
    return {"name": name, "base": "baseline", "seeds": 1, "grid": {"loops": loops},
            "set": {"duration_s": duration_s, "detailed_loops": 0, **MODEL_TIMING}}


class Server:
    """A `cosim5g serve` process over one results folder; can be killed and started again."""

    def __init__(self, root: Path) -> None:
        self.root = root
        self.port = free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        self.proc: subprocess.Popen[bytes] | None = None

    def start(self) -> None:
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "interfaces.cli", "serve", "--port", str(self.port),
             "--results", str(self.root / "runs"), "--db", str(self.root / "store.db"),
             "--sweeps", str(self.root / "sweeps"), "--scenarios", str(ROOT / "configs" / "scenarios"),
             "--sweep-specs", str(ROOT / "configs" / "sweeps")],
            cwd=ROOT, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
        deadline = time.monotonic() + 60
        while time.monotonic() < deadline:
            try:
                if call(self.base, "GET", "/healthz")[0] == 200:
                    return
            except ApiError:
                time.sleep(0.2)
        raise AssertionError("the coordinator did not come up")

    def stop(self) -> None:
        if self.proc is not None and self.proc.poll() is None:
            self.proc.terminate()
            self.proc.wait(60)

    def kill(self) -> None:
        assert self.proc is not None
        self.proc.send_signal(signal.SIGKILL)
        self.proc.wait()

    def api(self, method: str, path: str, body: Any = None) -> tuple[int, Any]:
        return call(self.base, method, path, body)

    def wait_sweep(self, sweep_id: str, until: Any, timeout_s: float = 400) -> dict[str, Any]:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            status, s = self.api("GET", f"/sweeps/{sweep_id}")
            assert status == 200, s
            if until(s):
                return dict(s)
            time.sleep(0.5)
        raise AssertionError(f"sweep {sweep_id} did not get there: {s['state']} {s['progress']}")


@pytest.fixture(scope="module")
def finished_sweep(tmp_path_factory: pytest.TempPathFactory) -> Any:
    server = Server(tmp_path_factory.mktemp("api"))
    server.start()
    try:
        status, body = server.api("POST", "/sweeps", {"spec": tiny_spec("rest", [1, 2])})
        assert status == 201, body
        assert body["points"] == 2 and body["state"] == "pending"
        s = server.wait_sweep(body["sweep_id"], lambda s: s["state"] not in ("pending", "running"))
        yield server, s
    finally:
        server.stop()


def test_sweep_runs_through_the_api_to_completed_with_its_report(finished_sweep: Any) -> None:
    server, s = finished_sweep
    sid = s["sweep_id"]
    assert s["state"] == "completed", s
    assert s["progress"] == {"points_total": 2, "points_done": 2, "points_failed": 0, "points_passed_over": 0,
                             "eta_s": None}
    assert [p["state"] for p in s["points"]] == ["completed", "completed"]
    assert all(p["kpis"]["ul_injected_mbps"] > 0 for p in s["points"])
    assert s["capacity"]["series"]["all"]["success>=100%"]["capacity"] in (0, 1, 2)
    status, report = server.api("GET", f"/sweeps/{sid}/report")
    assert status == 200 and "## Capacity" in report
    assert any(x["sweep_id"] == sid and x["state"] == "completed" for x in server.api("GET", "/sweeps")[1])
    for name in ("fig4_success.png", "fig5_traffic.svg", "fig6_latency_cdf.png", "capacity.json"):
        assert server.api("GET", f"/sweeps/{sid}/files/{name}")[0] == 200
    assert server.api("GET", f"/sweeps/{sid}/files/kpis.json")[0] == 404, "only the listed files"
    assert server.api("GET", f"/sweeps/{sid}/files/..%2Fsweep.json")[0] == 404
    assert server.api("GET", "/sweeps/nonesuch")[0] == 404
    assert server.api("POST", f"/sweeps/{sid}/cancel")[0] == 409
    metrics = server.api("GET", "/metrics")[1]
    assert 'cosim_coordinator_sweep_points_total{state="completed"} 2.0' in metrics


def test_bad_sweep_requests_are_refused_with_the_field_named(finished_sweep: Any) -> None:
    server, _ = finished_sweep
    status, body = server.api("POST", "/sweeps", {"spec": "../../etc/x"})
    assert status == 422 and body["detail"][0]["field"] == "spec"
    status, body = server.api("POST", "/sweeps", {"spec": {**tiny_spec("x", [1]), "base": "../../etc/passwd"}})
    assert status == 422 and body["detail"][0]["field"] == "base"
    status, body = server.api("POST", "/sweeps", {"spec": {**tiny_spec("x", [1]), "grid": {"loops": []}}})
    assert status == 422 and body["detail"][0]["field"] == "grid.loops"
    assert server.api("GET", "/sweeps/specs")[1] == ["codesign", "codesign_family", "factory_gnbs", "family",
                                                      "fast_cells", "load_feature", "overload", "quick", "reproduce",
                                                      "sensitivity", "sensitivity_detailed", "shared_edge"]


def test_results_page_in_a_real_browser(finished_sweep: Any, tmp_path: Path) -> None:
    browser = shutil.which("chromium") or shutil.which("chromium-browser")
    if browser is None:
        pytest.skip("no chromium (Debian: apt-get install chromium)")
    server, s = finished_sweep
    # A browser has no bearer header: /login turns the token into a cookie and comes back here.
    token = os.environ["COSIM5G_TOKEN"]
    url = f"{server.base}/login?token={token}&next=/sweeps/{s['sweep_id']}"
    shot = tmp_path / "page.png"
    flags = ["--headless", "--no-sandbox", "--disable-gpu", "--hide-scrollbars", "--window-size=1200,2600",
             f"--user-data-dir={tmp_path / 'profile'}"]
    proc = subprocess.run([browser, *flags, f"--screenshot={shot}", url], capture_output=True, timeout=120)
    assert shot.is_file() and shot.stat().st_size > 20_000, proc.stderr[-2000:]
    dom = subprocess.run([browser, *flags, "--dump-dom", url], capture_output=True, text=True, timeout=120).stdout
    assert 'id="capacity"' in dom and "success&gt;=100%" in dom
    figures = [f"/sweeps/{s['sweep_id']}/files/{stem}.png" for stem in ("fig4_success", "fig5_traffic",
                                                                      "fig6_latency_cdf")]
    assert all(f in dom for f in figures)
    # The screenshot shows what was drawn: the figures are far from a blank page.
    import numpy as np
    from PIL import Image

    pixels = np.asarray(Image.open(shot).convert("L"))
    assert (pixels < 128).mean() > 0.01, "the page has text and plots"
    index = subprocess.run([browser, *flags, "--dump-dom", f"{server.base}/login?token={token}&next=/"],
                           capture_output=True, text=True, timeout=120).stdout
    assert s["sweep_id"] in index


def test_a_sweep_survives_a_killed_coordinator_and_runs_every_point_once(tmp_path: Path) -> None:
    server = Server(tmp_path)
    server.start()
    try:
        status, body = server.api("POST", "/sweeps", {"spec": tiny_spec("restart", [1, 2, 3], duration_s=4.0)})
        assert status == 201, body
        sid = body["sweep_id"]
        server.wait_sweep(sid, lambda s: s["progress"]["points_done"] >= 1)
        server.kill()
        log = tmp_path / "sweeps" / sid / "points.jsonl"
        before = log.read_text().splitlines()
        # The point in flight dies with its coordinator; nothing of the run is left.
        deadline = time.monotonic() + 20
        while time.monotonic() < deadline and processes_with(tmp_path / "sweeps" / sid):
            time.sleep(0.5)
        assert processes_with(tmp_path / "sweeps" / sid) == []
        server.start()
        s = server.wait_sweep(sid, lambda s: s["state"] not in ("pending", "running"))
        assert s["state"] == "completed", s
        lines = [json.loads(line) for line in log.read_text().splitlines()]
        assert [json.loads(line) for line in before] == lines[:len(before)], "recorded points are kept"
        keys = [r["key"] for r in lines]
        assert len(keys) == len(set(keys)) == 3, "every point exactly once"
        assert all(r["status"] == "completed" for r in lines)
        assert [p["state"] for p in s["points"]] == ["completed"] * 3
    finally:
        server.stop()


def test_submit_sweep_from_the_cli_and_cancel_it(finished_sweep: Any) -> None:
    server, _ = finished_sweep
    out = subprocess.run([sys.executable, "-m", "interfaces.cli", "submit", "--sweep", "quick", "--api",
                          server.base], cwd=ROOT, capture_output=True, text=True, timeout=120)
    assert out.returncode == 0, out.stderr
    sid = out.stdout.strip().splitlines()[-1]
    server.wait_sweep(sid, lambda s: s["state"] == "running", timeout_s=60)
    status, body = server.api("POST", f"/sweeps/{sid}/cancel")
    assert status == 200 and body["cancelling"]
    s = server.wait_sweep(sid, lambda s: s["state"] not in ("pending", "running"), timeout_s=120)
    assert s["state"] == "cancelled" and s["progress"]["points_total"] == 18
    assert all(p["state"] in ("pending", "completed") for p in s["points"]), "a cancelled point is not recorded"
