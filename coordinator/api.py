"""The coordinator's REST API: start runs, follow them, read their KPIs; Prometheus ``/metrics``.

Runs execute one at a time on a worker thread (a run already uses every core of a small host).
Request bodies are validated by the same scenario schema as the CLI, and invalid ones get a 422
listing each field and what is allowed.
"""

from __future__ import annotations

import json
import queue
import threading
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

from fastapi import FastAPI, HTTPException
from fastapi.responses import JSONResponse, PlainTextResponse
from prometheus_client import CONTENT_TYPE_LATEST, Counter, Gauge, generate_latest
from pydantic import BaseModel, ConfigDict, Field

from coordinator.api_sweeps import add_sweep_routes
from coordinator.conductor import Progress
from coordinator.run import execute_run, new_run_id
from coordinator.store import RunStore
from experiments.service import SweepService
from services.common.scenario import ScenarioError, load_scenario, parse_scenario

RUNS = Counter("cosim_coordinator_runs_total", "Runs finished, by final state", ["status"])
ACTIVE = Gauge("cosim_coordinator_runs_active", "Runs pending or running")
SIM_TIME = Gauge("cosim_coordinator_run_sim_time_seconds", "Simulated time reached by the current run")
RTF = Gauge("cosim_coordinator_run_real_time_factor", "Real-time factor of the current run")


class RunRequest(BaseModel):
    """Start a run from a shipped scenario and/or an inline scenario, plus overrides."""

    model_config = ConfigDict(extra="forbid")
    scenario: str | None = Field(default=None, description="name of a file in configs/scenarios/")
    config: dict[str, Any] | None = Field(default=None, description="inline scenario fields")
    overrides: list[str] = Field(default_factory=list, description="field.path=value assignments")


class Coordinator:
    """Owns the store, the run queue and the worker thread."""

    def __init__(self, results_root: Path, db_path: Path, scenarios_dir: Path) -> None:
        self.results_root = results_root
        self.scenarios_dir = scenarios_dir
        self.store = RunStore(db_path)
        self.store.reap_orphans()
        self.queue: queue.SimpleQueue[tuple[str, Any] | None] = queue.SimpleQueue()
        self.busy = threading.Lock()  # held while a simulation runs (a run here, or a sweep point)
        self.cancels: dict[str, threading.Event] = {}
        self.worker = threading.Thread(target=self._work, daemon=True, name="runs")
        self.worker.start()

    def submit(self, req: RunRequest) -> dict[str, Any]:
        if req.scenario is not None:
            path = self.scenarios_dir / f"{req.scenario}.yaml"
            if not path.is_file():
                known = sorted(p.stem for p in self.scenarios_dir.glob("*.yaml"))
                raise ScenarioError([("scenario", f"{req.scenario!r} is not one of {known}")])
            sc = load_scenario(path, [*(f"{k}={v}" for k, v in _flatten(req.config or {})), *req.overrides])
        else:
            sc = parse_scenario(req.config or {}, req.overrides)
        run_id = new_run_id(sc)
        self.store.add(run_id, sc.name, sc.model_dump(mode="json"), str(self.results_root / run_id))
        self.cancels[run_id] = threading.Event()
        ACTIVE.inc()
        self.queue.put((run_id, sc))
        return {"run_id": run_id, "status": "pending"}

    def cancel(self, run_id: str) -> bool:
        ev = self.cancels.get(run_id)
        if ev is None:
            return False
        ev.set()
        return True

    def _work(self) -> None:
        while True:
            item = self.queue.get()
            if item is None:
                return
            run_id, sc = item
            cancel = self.cancels[run_id]
            try:
                if cancel.is_set():
                    self.store.finish(run_id, "cancelled", "cancelled before it started", {})
                    RUNS.labels("cancelled").inc()
                    continue
                self.store.set_running(run_id)

                def progress(p: Progress, run_id: str = run_id) -> None:
                    rtf = (p.t_us / 1e6) / p.wall_s if p.wall_s > 0 else 0.0
                    SIM_TIME.set(p.t_us / 1e6)
                    RTF.set(rtf)
                    self.store.set_progress(run_id, p.t_us / 1e6, rtf)

                with self.busy:
                    result = execute_run(sc, self.results_root, on_progress=progress, cancel=cancel, run_id=run_id)
                self.store.finish(run_id, result.status, result.reason, result.kpis)
                RUNS.labels(result.status).inc()
            except Exception as exc:  # the worker must survive a broken run
                self.store.finish(run_id, "failed", f"coordinator error: {exc}", {})
                RUNS.labels("failed").inc()
            finally:
                ACTIVE.dec()
                self.cancels.pop(run_id, None)

    def close(self) -> None:
        for ev in self.cancels.values():
            ev.set()
        self.queue.put(None)
        self.worker.join(timeout=60)
        self.store.close()


def _flatten(d: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    out: list[tuple[str, Any]] = []
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out += _flatten(v, key + ".")
        else:
            out.append((key, json.dumps(v)))
    return out


def create_app(results_root: Path, db_path: Path, scenarios_dir: Path, sweeps_root: Path | None = None,
               sweeps_dir: Path | None = None, sweep_jobs: int = 1) -> FastAPI:
    coord = Coordinator(results_root, db_path, scenarios_dir)
    sweeps_root = sweeps_root or results_root.parent / "sweeps"
    sweeps_dir = sweeps_dir or scenarios_dir.parent / "sweeps"
    # Single runs and sweep points share the host: one of them at a time.
    sweeps = SweepService(db_path, sweeps_root, scenarios_dir, jobs=sweep_jobs, busy=coord.busy)

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        yield
        sweeps.close()
        coord.close()

    app = FastAPI(title="cosim5g coordinator", version="0.1.0", lifespan=lifespan)
    app.state.coordinator = coord
    app.state.sweeps = sweeps
    add_sweep_routes(app, sweeps, sweeps_dir, scenarios_dir,
                     recent_runs=lambda: coord.store.list(limit=20))

    @app.exception_handler(ScenarioError)
    async def invalid_scenario(_: Any, exc: ScenarioError) -> JSONResponse:
        return JSONResponse(status_code=422, content={"detail": [{"field": f, "message": m} for f, m in exc.errors]})

    @app.get("/healthz")
    def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @app.get("/metrics")
    def metrics() -> PlainTextResponse:
        return PlainTextResponse(generate_latest().decode(), media_type=CONTENT_TYPE_LATEST)

    @app.get("/scenarios")
    def scenarios() -> list[str]:
        return sorted(p.stem for p in scenarios_dir.glob("*.yaml"))

    @app.post("/runs", status_code=201)
    def start_run(req: RunRequest) -> dict[str, Any]:
        return coord.submit(req)

    @app.get("/runs")
    def list_runs() -> list[dict[str, Any]]:
        return [{k: r[k] for k in ("run_id", "scenario", "status", "reason", "sim_time_s", "real_time_factor")}
                for r in coord.store.list()]

    @app.get("/runs/{run_id}")
    def get_run(run_id: str) -> dict[str, Any]:
        row = coord.store.get(run_id)
        if row is None:
            raise HTTPException(404, f"no run {run_id!r}")
        return row

    @app.post("/runs/{run_id}/cancel")
    def cancel_run(run_id: str) -> dict[str, Any]:
        if coord.store.get(run_id) is None:
            raise HTTPException(404, f"no run {run_id!r}")
        if not coord.cancel(run_id):
            raise HTTPException(409, f"run {run_id!r} has already ended")
        return {"run_id": run_id, "cancelling": True}

    return app
