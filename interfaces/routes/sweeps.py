"""``/sweeps``: start a sweep from a shipped or inline spec, follow it (JSON, or the results page
for a browser), cancel it, read its report and files.

A shipped spec is named (a file of configs/sweeps; no path from a request reaches the file
system); an inline spec's base is a shipped scenario.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Any

import yaml
from fastapi import APIRouter, HTTPException, Request
from fastapi.responses import FileResponse, HTMLResponse, PlainTextResponse, Response
from pydantic import BaseModel, ConfigDict, Field

from coordinator.run_state import RunState
from experiments.job_store import JobKind
from experiments.jobs import JobService
from experiments.spec import SweepError, SweepSpec, parse_spec
from interfaces.pages import sweep_page
from scenario.schema import Scenario, shipped_names

# What a client may fetch of a sweep's directory: the derived files, by exact name.
SWEEP_FILES = {f"{stem}.{ext}" for stem in ("fig4_success", "fig5_traffic", "fig6_latency_cdf", "fig7_gain",
                                            "fig8_map") for ext in ("png", "svg")} | {"capacity.json", "report.md", "points.parquet", "summary.parquet",
                                             "loops.parquet", "radio_cell_capacity.json"}
MEDIA = {".png": "image/png", ".svg": "image/svg+xml", ".json": "application/json", ".md": "text/markdown",
         ".parquet": "application/vnd.apache.parquet"}


class SweepRequest(BaseModel):
    """Start a sweep: a shipped spec by name, or an inline spec (its base a shipped scenario)."""

    model_config = ConfigDict(extra="forbid")
    spec: str | dict[str, Any] = Field(description="name of a file in configs/sweeps/, or the spec itself")


class SweepAccepted(BaseModel):
    sweep_id: str
    state: str = Field(description="pending")
    points: int = Field(description="points of its grid and base seeds")


class SweepProgress(BaseModel):
    points_total: int = Field(description="points to run: the grid's, less those passed over, plus seeds added")
    points_done: int
    points_failed: int
    points_passed_over: int = Field(default=0, description="points of a completed sweep that never ran: "
                                    "their series had stopped (capacity.stop_after)")
    eta_s: float | None = Field(description="estimated wall time left while it runs, s")


class PointState(BaseModel):
    values: dict[str, Any] = Field(description="the point's grid values")
    seed: int
    key: str
    state: str = Field(description="pending, running, completed, failed, timed_out, cancelled or "
                       "passed_over (a completed sweep's point whose series had stopped)")
    reason: str | None = None
    run_id: str | None = None
    sim_time_s: float | None = Field(default=None, description="while it runs: simulated time reached, s")
    kpis: dict[str, Any] | None = Field(default=None, description="its main KPIs once it has ended")


class SweepSummary(BaseModel):
    sweep_id: str
    name: str
    state: str = Field(description="pending, running, completed, failed or cancelled")
    reason: str | None
    created_s: float
    progress: SweepProgress


class SweepDetail(SweepSummary):
    started_s: float | None
    finished_s: float | None
    spec: dict[str, Any]
    points: list[PointState]
    capacity: dict[str, Any] | None = Field(description="capacity per series, once the sweep has ended")


class SweepCancelling(BaseModel):
    sweep_id: str
    cancelling: bool


def resolve_spec(req: SweepRequest, sweeps_dir: Path, scenarios_dir: Path,
                 max_points: tuple[int, str] | None = None,
                 check: Callable[[Scenario], list[tuple[str, str]]] | None = None) -> SweepSpec:
    if isinstance(req.spec, str):
        known = shipped_names(sweeps_dir)
        if req.spec not in known:  # checked against the list: a name never becomes a path
            raise SweepError([("spec", f"{req.spec!r} is not one of {known}")])
        data = yaml.safe_load((sweeps_dir / f"{req.spec}.yaml").read_text())
    else:
        data = req.spec
    return parse_spec(data, scenarios_dir, allow_paths=False, max_points=max_points, check=check)


def wants_html(request: Request) -> bool:
    """A browser (HTML named before JSON, or JSON not named at all) gets the page."""
    accept = request.headers.get("accept", "")
    if "text/html" not in accept:
        return False
    return "application/json" not in accept or accept.index("text/html") < accept.index("application/json")


def sweeps_router(jobs: JobService, sweeps_dir: Path, scenarios_dir: Path,
                  check: Callable[[Scenario], list[tuple[str, str]]], max_points: tuple[int, str],
                  on_change: Callable[[], None] = lambda: None) -> APIRouter:
    """``check(scenario)``: (field, message) of each limit a point passes (422), applied to every
    resolved point; ``max_points``
    (limit, setting) refuses a spec with more points before any point is validated;
    ``on_change()`` when sweeps are listed (the metrics; admission counts itself)."""
    router = APIRouter(tags=["sweeps"])

    def detail(sweep_id: str) -> dict[str, Any]:
        d = jobs.describe(sweep_id)
        if d is None:
            raise HTTPException(404, f"no sweep {sweep_id!r}")
        return d

    @router.get("/sweeps/specs")
    def sweep_specs() -> list[str]:
        return shipped_names(sweeps_dir)

    @router.post("/sweeps", status_code=201)
    def start_sweep(req: SweepRequest) -> SweepAccepted:
        spec = resolve_spec(req, sweeps_dir, scenarios_dir, max_points, check)
        sweep_id, points = jobs.submit_sweep(spec)
        return SweepAccepted(sweep_id=sweep_id, state=RunState.PENDING, points=points)

    @router.get("/sweeps")
    def list_sweeps() -> list[SweepSummary]:
        on_change()
        return [SweepSummary.model_validate(detail(s["job_id"])) for s in jobs.store.list(JobKind.SWEEP)]

    @router.get("/sweeps/{sweep_id}", response_model=SweepDetail,
                responses={200: {"content": {"text/html": {}},
                                 "description": "the sweep; its results page for a browser (Accept: text/html)"}})
    def get_sweep(sweep_id: str, request: Request) -> Any:
        d = detail(sweep_id)
        if wants_html(request):
            return HTMLResponse(sweep_page(d))
        return d

    @router.post("/sweeps/{sweep_id}/cancel")
    def cancel_sweep(sweep_id: str) -> SweepCancelling:
        if jobs.store.get(sweep_id, JobKind.SWEEP) is None:
            raise HTTPException(404, f"no sweep {sweep_id!r}")
        if not jobs.cancel(sweep_id):
            raise HTTPException(409, f"sweep {sweep_id!r} has already ended")
        return SweepCancelling(sweep_id=sweep_id, cancelling=True)

    def sweep_dir(sweep_id: str) -> Path:
        row = jobs.store.get(sweep_id, JobKind.SWEEP)
        if row is None:
            raise HTTPException(404, f"no sweep {sweep_id!r}")
        return Path(row["dir"])

    @router.get("/sweeps/{sweep_id}/report", response_class=PlainTextResponse)
    def sweep_report(sweep_id: str) -> PlainTextResponse:
        path = sweep_dir(sweep_id) / "report.md"
        if not path.is_file():
            raise HTTPException(409, f"sweep {sweep_id!r} has no report yet (it is written when the sweep ends)")
        return PlainTextResponse(path.read_text(), media_type="text/markdown")

    @router.get("/sweeps/{sweep_id}/files/{name}", response_model=None,
                responses={200: {"content": {m: {} for m in MEDIA.values()}, "description": "the file"}})
    def sweep_file(sweep_id: str, name: str) -> Response:
        if name not in SWEEP_FILES:
            raise HTTPException(404, f"{name!r} is not a sweep file; files: {', '.join(sorted(SWEEP_FILES))}")
        path = sweep_dir(sweep_id) / name
        if not path.is_file():
            raise HTTPException(404, f"sweep {sweep_id!r} has no {name} yet")
        return FileResponse(path, media_type=MEDIA[path.suffix])

    return router
