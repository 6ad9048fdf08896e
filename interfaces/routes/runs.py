"""``/runs`` and ``/scenarios``: start a run from a shipped or inline scenario, follow it, cancel it."""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path
from typing import Any

from fastapi import APIRouter, HTTPException
from pydantic import BaseModel, ConfigDict, Field

from coordinator.run_state import RunState
from experiments.job_store import JobKind
from experiments.jobs import JobService
from scenario.schema import Scenario, ScenarioError, load_scenario, parse_scenario, shipped_names


class RunRequest(BaseModel):
    """Start a run from a shipped scenario and/or an inline scenario, plus overrides."""

    model_config = ConfigDict(extra="forbid")
    scenario: str | None = Field(default=None, description="name of a file in configs/scenarios/")
    config: dict[str, Any] | None = Field(default=None, description="inline scenario fields")
    overrides: list[str] = Field(default_factory=list, description="field.path=value assignments")


class RunAccepted(BaseModel):
    run_id: str
    status: str = Field(description="pending")


class RunSummary(BaseModel):
    run_id: str
    scenario: str = Field(description="the scenario's name")
    status: str = Field(description="pending, running, completed, failed, timed_out or cancelled")
    reason: str | None = Field(description="why it failed, timed out or was cancelled")
    sim_time_s: float | None = Field(description="simulated time reached, s")
    real_time_factor: float | None = Field(description="simulated s per wall s so far")


class RunDetail(RunSummary):
    created_s: float = Field(description="when it was accepted, Unix time s")
    started_s: float | None
    finished_s: float | None
    config: dict[str, Any] = Field(description="the whole scenario the run was given")
    kpis: dict[str, Any] | None = Field(description="the run's KPIs once it has ended")
    results_dir: str = Field(description="its results directory on the coordinator's host")


class RunCancelling(BaseModel):
    run_id: str
    cancelling: bool


def run_detail(row: dict[str, Any]) -> RunDetail:
    return RunDetail(run_id=row["job_id"], scenario=row["name"], status=row["state"], reason=row["reason"],
                     sim_time_s=row["sim_time_s"], real_time_factor=row["real_time_factor"],
                     created_s=row["created_s"], started_s=row["started_s"], finished_s=row["finished_s"],
                     config=row["request"], kpis=row["kpis"], results_dir=row["dir"])


def runs_router(jobs: JobService, scenarios_dir: Path,
                check: Callable[[Scenario], list[tuple[str, str]]]) -> APIRouter:
    """``check(scenario)``: (field, message) of each limit the scenario passes (422)."""
    router = APIRouter(tags=["runs"])

    def scenario_of(req: RunRequest) -> Scenario:
        if req.scenario is not None:
            known = shipped_names(scenarios_dir)
            if req.scenario not in known:  # checked against the list: a name never becomes a path
                raise ScenarioError([("scenario", f"{req.scenario!r} is not one of {known}")])
            return load_scenario(scenarios_dir / f"{req.scenario}.yaml",
                                 [*(f"{k}={v}" for k, v in _flatten(req.config or {})), *req.overrides])
        return parse_scenario(req.config or {}, req.overrides)

    @router.get("/scenarios")
    def scenarios() -> list[str]:
        return shipped_names(scenarios_dir)

    @router.post("/runs", status_code=201)
    def start_run(req: RunRequest) -> RunAccepted:
        sc = scenario_of(req)
        errors = check(sc)
        if errors:
            raise ScenarioError(errors)
        return RunAccepted(run_id=jobs.submit_run(sc), status=RunState.PENDING)

    @router.get("/runs")
    def list_runs() -> list[RunSummary]:
        return [RunSummary(**run_detail(r).model_dump(include=set(RunSummary.model_fields)))
                for r in jobs.store.list(JobKind.RUN, limit=100)]

    @router.get("/runs/{run_id}")
    def get_run(run_id: str) -> RunDetail:
        row = jobs.store.get(run_id, JobKind.RUN)
        if row is None:
            raise HTTPException(404, f"no run {run_id!r}")
        return run_detail(row)

    @router.post("/runs/{run_id}/cancel")
    def cancel_run(run_id: str) -> RunCancelling:
        if jobs.store.get(run_id, JobKind.RUN) is None:
            raise HTTPException(404, f"no run {run_id!r}")
        if not jobs.cancel(run_id):
            raise HTTPException(409, f"run {run_id!r} has already ended")
        return RunCancelling(run_id=run_id, cancelling=True)

    return router


def _flatten(d: dict[str, Any], prefix: str = "") -> list[tuple[str, Any]]:
    out: list[tuple[str, Any]] = []
    for k, v in d.items():
        key = f"{prefix}{k}"
        if isinstance(v, dict):
            out += _flatten(v, key + ".")
        else:
            out.append((key, json.dumps(v)))
    return out
