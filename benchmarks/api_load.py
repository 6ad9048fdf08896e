"""Load test of the coordinator's REST API (``make load``): N clients send one ``cosim5g serve`` a
mix of requests (runs and sweeps started, status polled, pages, refusals).

Reports answers by kind and status, p50/p99 response times, RSS, the most jobs pending or running
against the queue limit and whether every accepted job ended in the store
(results/bench/api_load.{json,md}).
"""

from __future__ import annotations

import argparse
import json
import os
import random
import secrets
import subprocess
import sys
import tempfile
import threading
import time
import urllib.error
import urllib.request
from collections import Counter
from pathlib import Path
from typing import Any

from benchmarks.reliability import write
from coordinator.run import free_port
from experiments.job_store import JobKind, JobStore

ROOT = Path(__file__).parents[1]
# Requests by kind, with their weights in the mix.
MIX = {"status": 30, "list_runs": 10, "list_sweeps": 8, "page": 7, "metrics": 5, "start_run": 12,
       "start_sweep": 5, "no_token": 8, "too_large": 5, "invalid": 10}
# Short runs of abstract loops with modelled compute: seconds each, so that the queue moves.
QUICK = {"duration_s": 1, "loops": 2, "detailed_loops": 0, "nodes.camera.timing": "model",
         "nodes.edge.timing": "model", "nodes.robot.timing": "model"}
RUN = {"scenario": "baseline", "overrides": [f"{k}={v}" for k, v in QUICK.items()]}
SWEEP = {"spec": {"name": "load", "base": "baseline", "seeds": 1, "grid": {"loops": [2]},
                  "set": {k: v for k, v in QUICK.items() if k != "loops"}}}


class Coordinator:
    """A ``cosim5g serve`` process on a free loopback port, over a fresh results folder."""

    def __init__(self, root: Path, max_queued: int, max_body_bytes: int) -> None:
        self.port = free_port()
        self.base = f"http://127.0.0.1:{self.port}"
        self.token = secrets.token_urlsafe(24)
        self.root = root
        env = {**os.environ, "COSIM5G_TOKEN": self.token}
        self.proc = subprocess.Popen(
            [sys.executable, "-m", "interfaces.cli", "serve", "--port", str(self.port),
             "--results", str(root / "runs"), "--db", str(root / "jobs.db"), "--sweeps", str(root / "sweeps"),
             "--scenarios", str(ROOT / "configs" / "scenarios"), "--sweep-specs", str(ROOT / "configs" / "sweeps"),
             "--token-file", str(root / "auth" / "api-token"), "--max-queued", str(max_queued),
             "--max-body-bytes", str(max_body_bytes), "--slots", "1"],
            cwd=ROOT, env=env, stdout=subprocess.DEVNULL, stderr=open(root / "serve.log", "wb"))
        deadline = time.monotonic() + 60
        while self.call("GET", "/healthz", token=False)[0] != 200:
            if self.proc.poll() is not None or time.monotonic() > deadline:
                raise RuntimeError(f"the coordinator did not come up: {(root / 'serve.log').read_text()[-2000:]}")
            time.sleep(0.2)

    def call(self, method: str, path: str, body: bytes | None = None, token: bool = True,
             content_type: str = "application/json") -> tuple[int, Any, float]:
        """Status, decoded JSON (or text) and response time of one request; status 0 when the
        connection failed."""
        headers = {"content-type": content_type} if body is not None else {}
        if token:
            headers["Authorization"] = f"Bearer {self.token}"
        req = urllib.request.Request(self.base + path, data=body, method=method, headers=headers)
        t0 = time.monotonic()
        try:
            with urllib.request.urlopen(req, timeout=60) as resp:
                status, raw = resp.status, resp.read()
        except urllib.error.HTTPError as err:
            status, raw = err.code, err.read()
        except OSError:
            return 0, None, time.monotonic() - t0
        dt = time.monotonic() - t0
        try:
            return status, json.loads(raw), dt
        except ValueError:
            return status, raw.decode(errors="replace"), dt

    def rss_mb(self) -> float:
        for line in Path(f"/proc/{self.proc.pid}/status").read_text().splitlines():
            if line.startswith("VmRSS:"):
                return int(line.split()[1]) / 1024
        return 0.0

    def stop(self) -> None:
        self.proc.terminate()
        self.proc.wait(60)


class Load:
    """The clients' shared record: every answer, and the jobs accepted."""

    def __init__(self) -> None:
        self.lock = threading.Lock()
        self.answers: list[tuple[str, int, float]] = []  # kind, status, response time
        self.runs: list[str] = []
        self.sweeps: list[str] = []

    def add(self, kind: str, status: int, dt: float, body: Any) -> None:
        with self.lock:
            self.answers.append((kind, status, dt))
            if status == 201 and kind == "start_run":
                self.runs.append(body["run_id"])
            elif status == 201 and kind == "start_sweep":
                self.sweeps.append(body["sweep_id"])


def one_request(c: Coordinator, load: Load, kind: str, rng: random.Random, max_body_bytes: int) -> None:
    if kind == "status":
        with load.lock:
            known = [("runs", r) for r in load.runs] + [("sweeps", s) for s in load.sweeps]
        what, job = rng.choice(known) if known else ("runs", "none")
        status, body, dt = c.call("GET", f"/{what}/{job}")
    elif kind in ("list_runs", "list_sweeps"):
        status, body, dt = c.call("GET", "/runs" if kind == "list_runs" else "/sweeps")
    elif kind == "page":
        status, body, dt = c.call("GET", "/")
    elif kind == "metrics":
        status, body, dt = c.call("GET", "/metrics")
    elif kind == "start_run":
        status, body, dt = c.call("POST", "/runs", json.dumps(RUN).encode())
    elif kind == "start_sweep":
        status, body, dt = c.call("POST", "/sweeps", json.dumps(SWEEP).encode())
    elif kind == "no_token":
        status, body, dt = c.call("POST", "/runs", json.dumps(RUN).encode(), token=False)
    elif kind == "too_large":
        status, body, dt = c.call("POST", "/runs", b" " * (max_body_bytes + 1))
    else:  # invalid: a field that does not exist, or a value out of range
        bad = rng.choice(["camera.fsp=3", "duration_s=-1", "loops=[x", "watchdog.window_timeout_s=inf"])
        status, body, dt = c.call("POST", "/runs", json.dumps({"scenario": "baseline", "overrides": [bad]}).encode())
    load.add(kind, status, dt, body)


def warm_up(c: Coordinator, drain_s: float) -> None:
    """One run and one sweep to their end, and every kind of request once: the coordinator's
    memory after them is the baseline (a run in this process loads what every later run uses)."""
    for body in (RUN, SWEEP):
        status, answer, _ = c.call("POST", "/runs" if body is RUN else "/sweeps", json.dumps(body).encode())
        if status != 201:
            raise RuntimeError(f"the warm-up's {'run' if body is RUN else 'sweep'} was refused: {status} {answer}")
    drain(c, drain_s)
    load, rng = Load(), random.Random(0)
    for kind in MIX:
        if not kind.startswith("start_"):
            one_request(c, load, kind, rng, 1_000_000)


def drain(c: Coordinator, timeout_s: float) -> None:
    """Wait until no run or sweep is pending or running."""
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        runs, sweeps = c.call("GET", "/runs")[1], c.call("GET", "/sweeps")[1]
        if not any(r["status"] in ("pending", "running") for r in runs) and \
                not any(s["state"] in ("pending", "running") for s in sweeps):
            return
        time.sleep(1.0)


def active_at_most(rows: list[dict[str, Any]], end_s: float) -> int:
    """The most jobs pending or running at one time, from their accept and end times."""
    events = sorted([(r["created_s"], 1) for r in rows] + [(r["finished_s"] or end_s, -1) for r in rows])
    most = now = 0
    for _, step in events:
        now += step
        most = max(most, now)
    return most


def percentile(values: list[float], q: float) -> float:
    if not values:
        return float("nan")
    s = sorted(values)
    return s[min(len(s) - 1, int(q * len(s)))]


def run_load(requests: int, clients: int, max_queued: int = 4, seed: int = 1,
             max_body_bytes: int = 1_000_000, drain_s: float = 600.0) -> dict[str, Any]:
    """The load test; its record (see the module's docstring)."""
    with tempfile.TemporaryDirectory(prefix="cosim5g-load-") as tmp:
        root = Path(tmp)
        c = Coordinator(root, max_queued, max_body_bytes)
        try:
            warm_up(c, drain_s)
            rss0 = c.rss_mb()
            load = Load()
            kinds = list(MIX)
            weights = [MIX[k] for k in kinds]
            plan = random.Random(seed).choices(kinds, weights, k=requests)
            per_client = [plan[i::clients] for i in range(clients)]
            t0 = time.monotonic()

            def client(i: int) -> None:
                rng = random.Random(seed * 1000 + i)
                for kind in per_client[i]:
                    one_request(c, load, kind, rng, max_body_bytes)

            threads = [threading.Thread(target=client, args=(i,)) for i in range(clients)]
            for t in threads:
                t.start()
            for t in threads:
                t.join()
            wall_s = time.monotonic() - t0
            rss1 = c.rss_mb()
            drain(c, drain_s)  # the accepted jobs run to their end
            rss2 = c.rss_mb()
        finally:
            c.stop()
        store = JobStore(root / "jobs.db")
        rows = [r for kind in JobKind for r in store.list(kind, limit=100_000)]
        store.close()
    by_id = {r["job_id"]: r for r in rows}
    accepted = load.runs + load.sweeps
    lost = [j for j in accepted if j not in by_id]
    unfinished = [j for j in accepted if j in by_id and by_id[j]["state"] in ("pending", "running")]
    status_dts = [dt for kind, s, dt in load.answers if kind == "status"]
    all_dts = [dt for _, _, dt in load.answers]
    counts = Counter(f"{kind} {status}" for kind, status, _ in load.answers)
    return {
        "requests": len(load.answers), "clients": clients, "max_queued": max_queued, "wall_s": round(wall_s, 2),
        "requests_per_s": round(len(load.answers) / wall_s, 1),
        "answers": dict(sorted(counts.items())),
        "errors_5xx": sum(1 for _, s, _ in load.answers if s >= 500),
        "failed_connections": sum(1 for _, s, _ in load.answers if s == 0),
        "status_p50_ms": round(1000 * percentile(status_dts, 0.5), 1),
        "status_p99_ms": round(1000 * percentile(status_dts, 0.99), 1),
        "all_p99_ms": round(1000 * percentile(all_dts, 0.99), 1),
        "all_max_ms": round(1000 * max(all_dts, default=float("nan")), 1),
        "rss_mb_before": round(rss0, 1), "rss_mb_after_load": round(rss1, 1), "rss_mb_after_drain": round(rss2, 1),
        "rss_growth": round((rss2 - rss0) / rss0, 3) if rss0 else None,
        "accepted_runs": len(load.runs), "accepted_sweeps": len(load.sweeps),
        "most_active_at_once": active_at_most(rows, time.time()),
        "lost": lost, "unfinished": unfinished,
    }


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__)
    ap.add_argument("--requests", type=int, default=1000)
    ap.add_argument("--clients", type=int, default=8)
    ap.add_argument("--max-queued", type=int, default=4)
    ap.add_argument("--seed", type=int, default=1)
    ap.add_argument("--json", action="store_true", help="print the record as JSON instead of writing it")
    args = ap.parse_args(argv)
    rec = run_load(args.requests, args.clients, args.max_queued, args.seed)
    if args.json:
        print(json.dumps(rec))
        return 0
    table = [(k, v) for k, v in rec.items() if k != "answers"] + [(f"  {k}", v) for k, v in rec["answers"].items()]
    write("api_load", rec, table)
    ok = (rec["errors_5xx"] == 0 and not rec["lost"] and not rec["unfinished"] and rec["failed_connections"] == 0
          and rec["most_active_at_once"] <= rec["max_queued"])
    return 0 if ok else 1


if __name__ == "__main__":
    sys.exit(main())
