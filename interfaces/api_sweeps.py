"""REST routes for sweeps and the results pages, on top of the sweep engine's service.

A sweep is started from a shipped spec (a name from configs/sweeps; no path from a request ever
reaches the file system) or an inline spec whose base is a shipped scenario. ``GET /`` and
``GET /sweeps/{id}`` answer a browser (Accept: text/html) with the results pages and anything
else with JSON.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import yaml
from fastapi import FastAPI, HTTPException, Request
from fastapi.responses import FileResponse, HTMLResponse, JSONResponse, PlainTextResponse, Response
from prometheus_client import Counter, Gauge
from pydantic import BaseModel, ConfigDict, Field

from experiments.service import SweepService
from experiments.spec import SweepError, SweepSpec, parse_spec
from interfaces.pages import index_page, sweep_page
from scenario.schema import shipped_names

SWEEPS_ACTIVE = Gauge("cosim_coordinator_sweeps_active", "Sweeps pending or running")
SWEEP_POINTS = Counter("cosim_coordinator_sweep_points_total", "Sweep points finished, by state", ["state"])
POINTS_REMAINING = Gauge("cosim_coordinator_sweep_points_remaining", "Points of active sweeps not yet finished")
# What a client may fetch of a sweep's directory: the derived files, by exact name.
SWEEP_FILES = {f"{stem}.{ext}" for stem in ("fig4_success", "fig5_traffic", "fig6_latency_cdf")
               for ext in ("png", "svg")} | {"capacity.json", "report.md", "points.parquet", "summary.parquet",
                                             "loops.parquet", "cell_capacity.json"}
MEDIA = {".png": "image/png", ".svg": "image/svg+xml", ".json": "application/json", ".md": "text/markdown",
         ".parquet": "application/vnd.apache.parquet"}


class SweepRequest(BaseModel):
    """Start a sweep: a shipped spec by name, or an inline spec (its base a shipped scenario)."""

    model_config = ConfigDict(extra="forbid")
    spec: str | dict[str, Any] = Field(description="name of a file in configs/sweeps/, or the spec itself")


def resolve_spec(req: SweepRequest, sweeps_dir: Path, scenarios_dir: Path,
                 max_points: tuple[int, str] | None = None) -> SweepSpec:
    if isinstance(req.spec, str):
        known = shipped_names(sweeps_dir)
        if req.spec not in known:  # checked against the list: a name never becomes a path
            raise SweepError([("spec", f"{req.spec!r} is not one of {known}")])
        data = yaml.safe_load((sweeps_dir / f"{req.spec}.yaml").read_text())
    else:
        data = req.spec
    return parse_spec(data, scenarios_dir, allow_paths=False, max_points=max_points)


def wants_html(request: Request) -> bool:
    """A browser (HTML named before JSON, or JSON not named at all) gets the page."""
    accept = request.headers.get("accept", "")
    if "text/html" not in accept:
        return False
    return "application/json" not in accept or accept.index("text/html") < accept.index("application/json")


def add_sweep_routes(app: FastAPI, service: SweepService, sweeps_dir: Path, scenarios_dir: Path,
                     check_spec: Any = None, recent_runs: Any = None,
                     max_points: tuple[int, str] | None = None) -> None:
    """``check_spec(spec)`` may refuse a spec (limits) by raising HTTPException; ``max_points``
    (limit, setting) refuses a spec with more points before any point is validated."""

    def summary(sid: str) -> dict[str, Any]:
        d = service.describe(sid)
        assert d is not None
        return {k: d[k] for k in ("sweep_id", "name", "state", "reason", "created_s", "progress")}

    def refresh_metrics() -> None:
        active = service.store.list(("pending", "running"))
        SWEEPS_ACTIVE.set(len(active))
        POINTS_REMAINING.set(sum(d["progress"]["points_total"] - d["progress"]["points_done"]
                                 for s in active if (d := service.describe(s["sweep_id"])) is not None))

    service.on_point_done = lambda state: SWEEP_POINTS.labels(state).inc()
    for state in ("completed", "failed", "timed_out"):  # every panel has its series from the start
        SWEEP_POINTS.labels(state)
    SWEEPS_ACTIVE.set(0)
    POINTS_REMAINING.set(0)

    @app.get("/sweeps/specs")
    def sweep_specs() -> list[str]:
        return shipped_names(sweeps_dir)

    @app.post("/sweeps", status_code=201)
    def start_sweep(req: SweepRequest) -> dict[str, Any]:
        spec = resolve_spec(req, sweeps_dir, scenarios_dir, max_points)
        if check_spec is not None:
            check_spec(spec, service)
        out = service.submit(spec)
        refresh_metrics()
        return out

    @app.get("/sweeps")
    def list_sweeps() -> list[dict[str, Any]]:
        refresh_metrics()
        return [summary(s["sweep_id"]) for s in service.store.list()]

    @app.get("/sweeps/{sweep_id}", response_model=None)
    def get_sweep(sweep_id: str, request: Request) -> dict[str, Any] | HTMLResponse:
        d = service.describe(sweep_id)
        if d is None:
            raise HTTPException(404, f"no sweep {sweep_id!r}")
        if wants_html(request):
            return HTMLResponse(sweep_page(d))
        return d

    @app.post("/sweeps/{sweep_id}/cancel")
    def cancel_sweep(sweep_id: str) -> dict[str, Any]:
        if service.store.get(sweep_id) is None:
            raise HTTPException(404, f"no sweep {sweep_id!r}")
        if not service.cancel(sweep_id):
            raise HTTPException(409, f"sweep {sweep_id!r} has already ended")
        return {"sweep_id": sweep_id, "cancelling": True}

    def sweep_dir(sweep_id: str) -> Path:
        row = service.store.get(sweep_id)
        if row is None:
            raise HTTPException(404, f"no sweep {sweep_id!r}")
        return Path(row["sweep_dir"])

    @app.get("/sweeps/{sweep_id}/report", response_class=PlainTextResponse)
    def sweep_report(sweep_id: str) -> PlainTextResponse:
        path = sweep_dir(sweep_id) / "report.md"
        if not path.is_file():
            raise HTTPException(409, f"sweep {sweep_id!r} has no report yet (it is written when the sweep ends)")
        return PlainTextResponse(path.read_text(), media_type="text/markdown")

    @app.get("/sweeps/{sweep_id}/files/{name}", response_model=None)
    def sweep_file(sweep_id: str, name: str) -> Response:
        if name not in SWEEP_FILES:
            raise HTTPException(404, f"{name!r} is not a sweep file; files: {', '.join(sorted(SWEEP_FILES))}")
        path = sweep_dir(sweep_id) / name
        if not path.is_file():
            raise HTTPException(404, f"sweep {sweep_id!r} has no {name} yet")
        return FileResponse(path, media_type=MEDIA[path.suffix])

    @app.get("/", response_class=HTMLResponse)
    def index() -> HTMLResponse:
        sweeps = [service.describe(s["sweep_id"]) for s in service.store.list()]
        runs = recent_runs() if recent_runs is not None else []
        return HTMLResponse(index_page([s for s in sweeps if s is not None], runs))

    @app.exception_handler(SweepError)
    async def invalid_sweep(_: Any, exc: SweepError) -> JSONResponse:
        return JSONResponse(status_code=422, content={"detail": [{"field": f, "message": m} for f, m in exc.errors]})
