"""The coordinator's REST API: the app, assembled from its routers (``interfaces.routes``), its
front door (``interfaces.guard``), its limits (``LIMITS``) and its metrics.

Runs and sweeps share one job service; bodies are validated by the scenario and sweep schemas,
limits give 422, 413 or 429 naming the limit: docs/architecture.md sec. 12.
"""

from __future__ import annotations

import logging
from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager, suppress
from pathlib import Path
from typing import Any

from fastapi import Depends, FastAPI
from fastapi.responses import JSONResponse
from fastapi.security import HTTPBearer
from prometheus_client import Counter, Gauge

from coordinator.run import RunResult, execute_run
from coordinator.run_state import ACTIVE, RunState
from domain.policy import policy_errors
from experiments.executors import Executor
from experiments.job_store import JobKind
from experiments.jobs import JobService, TooMuchWork
from experiments.slots import Slots
from experiments.spec import SweepError
from fabric.settings import Settings, settings
from interfaces.guard import PUBLIC_PATHS, Guard, redact_access_log
from interfaces.routes.runs import runs_router
from interfaces.routes.site import site_router
from interfaces.routes.sweeps import sweeps_router
from scenario.schema import Scenario, ScenarioError

log = logging.getLogger(__name__)

RUNS = Counter("cosim_coordinator_runs_total", "Runs finished, by final state", ["status"])
ACTIVE_RUNS = Gauge("cosim_coordinator_runs_active", "Runs pending or running")
# Per run while it runs (several may at once), the series removed when it ends.
SIM_TIME = Gauge("cosim_coordinator_run_sim_time_seconds", "Simulated time reached by a running run", ["run_id"])
RTF = Gauge("cosim_coordinator_run_real_time_factor", "Real-time factor of a running run", ["run_id"])
REFUSED = Counter("cosim_coordinator_requests_refused_total", "Requests refused by a limit or for the token",
                  ["reason"])
SWEEPS_ACTIVE = Gauge("cosim_coordinator_sweeps_active", "Sweeps pending or running")
SWEEP_POINTS = Counter("cosim_coordinator_sweep_points_total", "Sweep points finished, by state", ["state"])
POINTS_REMAINING = Gauge("cosim_coordinator_sweep_points_remaining", "Points of active sweeps not yet finished")
SLOTS_BUSY = Gauge("cosim_coordinator_slots_busy", "Simulation slots in use (runs and sweep points)")

BEARER = HTTPBearer(auto_error=False, scheme_name="token",
                    description="the coordinator's API token: results/auth/api-token on its host, or COSIM5G_TOKEN")


# A request names no file of the coordinator's host (a model elsewhere is for the CLI).
MODEL = "policy.learned_model"
NO_FILES = ("a request cannot name a file: leave it unset, and the coordinator's shipped model "
            "(domain/models/policy.onnx) is used")
# The settings a `cosim5g serve` flag may give (--max-queued, ...); the environment or the default else.
LIMITS = ("max_duration_s", "max_run_timeout_s", "max_sweep_points", "max_queued", "max_body_bytes", "slots")


def limit_source(name: str) -> str:
    """How a limit is set, for messages: ``max_queued (--max-queued, COSIM5G_MAX_QUEUED)``."""
    return f"{name} (--{name.replace('_', '-')}, COSIM5G_{name.upper()})"



def scenario_limit_errors(sc: Scenario, limits: Settings) -> list[tuple[str, str]]:
    """(field, message) for each field of ``sc`` beyond this coordinator's limits."""
    errors = []
    if sc.duration_s > limits.max_duration_s:
        errors.append(("duration_s", f"{sc.duration_s:g} s is more than this coordinator allows: "
                                     f"{limit_source('max_duration_s')} = {limits.max_duration_s:g} s"))
    if sc.policy.learned_model is not None:
        errors.append(("policy.learned_model", NO_FILES))
    if sc.watchdog.run_timeout_s > limits.max_run_timeout_s:
        errors.append(("watchdog.run_timeout_s", f"{sc.watchdog.run_timeout_s:g} s is more than this coordinator "
                       f"allows: {limit_source('max_run_timeout_s')} = {limits.max_run_timeout_s:g} s"))
    return errors


def document_refusals(schema: dict[str, Any]) -> dict[str, Any]:
    """The OpenAPI schema as the app answers: /healthz needs no token (the app-wide dependency
    marks every route), every other operation may answer 401, a POST 403 (the cookie alone from
    another origin), the two that queue work 429, and a
    422 lists either the framework's items (loc, msg, type) or the scenario and sweep checks'
    (field, message)."""
    detail = {"type": "object", "required": ["detail"], "properties": {"detail": {"type": "string"}}}
    for path, ops in schema["paths"].items():
        for method, op in ops.items():
            if path in PUBLIC_PATHS:
                op.pop("security", None)
                continue
            op["responses"]["401"] = {"description": "missing or wrong API token",
                                      "content": {"application/json": {"schema": detail}}}
            if method == "post":
                op["responses"]["403"] = {"description": "authorised by the login cookie alone from "
                                          "another origin (send the bearer header)",
                                          "content": {"application/json": {"schema": detail}}}
            if method == "post" and path in ("/runs", "/sweeps"):
                op["responses"]["429"] = {"description": "too much work queued (the limit max_queued)",
                                          "content": {"application/json": {"schema": detail}}}
    comps = schema.setdefault("components", {}).setdefault("schemas", {})
    comps["FieldError"] = {
        "title": "FieldError", "type": "object", "required": ["field", "message"],
        "properties": {"field": {"type": "string", "description": "the field, dotted (e.g. camera.fps)"},
                       "message": {"type": "string", "description": "what is wrong, and what is allowed"}}}
    if "HTTPValidationError" in comps:
        comps["HTTPValidationError"]["properties"]["detail"]["items"] = {
            "anyOf": [{"$ref": "#/components/schemas/ValidationError"}, {"$ref": "#/components/schemas/FieldError"}]}
    return schema


def create_app(results_root: Path, db_path: Path, scenarios_dir: Path, sweeps_root: Path | None = None,
               sweeps_dir: Path | None = None, *, token: str, limits: Settings | None = None,
               token_hint: str = "the coordinator's COSIM5G_TOKEN or the content of its token file",
               execute: Callable[..., RunResult] = execute_run,
               make_sweep_executor: Callable[[Slots], Executor] | None = None) -> Guard:
    """The app behind its guard; ``token`` is the bearer token every route but /healthz needs
    (``token_hint`` tells a refused client where to find it). ``execute`` runs one run and
    ``make_sweep_executor(slots)`` makes a sweep's executor (defaults: the real ones). The
    FastAPI app is the guard's ``app``."""
    limits = limits or settings()
    sweeps_root = sweeps_root or results_root.parent / "sweeps"
    sweeps_dir = sweeps_dir or scenarios_dir.parent / "sweeps"
    jobs = JobService(db_path, results_root, sweeps_root, scenarios_dir, slots=limits.slots,
                      max_queued=limits.max_queued, execute=execute, make_executor=make_sweep_executor)
    count_jobs(jobs)
    refused = (f"missing or wrong API token: send the header 'Authorization: Bearer <token>'; the token is "
               f"{token_hint}")

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        yield
        jobs.close()

    # The guard checks the token; the dependency only documents it (auto_error=False). The
    # framework's own /openapi.json and /docs are replaced by the site router's.
    app = FastAPI(title="cosim5g coordinator", version="0.1.0", lifespan=lifespan, dependencies=[Depends(BEARER)],
                  openapi_url=None, docs_url=None, redoc_url=None)
    app.state.jobs = jobs
    app.state.limits = limits

    def openapi_schema() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = document_refusals(FastAPI.openapi(app))
        return app.openapi_schema

    app.openapi = openapi_schema  # type: ignore[method-assign]
    app.include_router(site_router(jobs, token, refused, app.openapi, count_refusal))
    def within_limits(sc: Scenario) -> list[tuple[str, str]]:
        return scenario_limit_errors(sc, limits) or policy_errors(sc.policy, sc.work_cell)

    app.include_router(runs_router(jobs, scenarios_dir, within_limits))
    app.include_router(sweeps_router(jobs, sweeps_dir, scenarios_dir, within_limits,
                                     (limits.max_sweep_points, limit_source("max_sweep_points")),
                                     on_change=lambda: count_sweeps(jobs)))

    async def field_errors(_: Any, exc: Exception) -> JSONResponse:
        assert isinstance(exc, ScenarioError | SweepError)
        return JSONResponse(status_code=422, content={"detail": [{"field": f, "message": m} for f, m in exc.errors]})

    app.add_exception_handler(ScenarioError, field_errors)
    app.add_exception_handler(SweepError, field_errors)

    @app.exception_handler(TooMuchWork)
    async def too_much_work(_: Any, exc: TooMuchWork) -> JSONResponse:
        REFUSED.labels("max_queued").inc()
        return JSONResponse(status_code=429, content={"detail": str(exc)}, headers={"Retry-After": "60"})

    redact_access_log()
    return Guard(app, token=token, max_body_bytes=limits.max_body_bytes, refused=refused, on_refused=count_refusal)


def count_refusal(reason: str) -> None:
    REFUSED.labels(reason).inc()


def count_jobs(jobs: JobService) -> None:
    """The coordinator's metrics follow the job service; every series exists from the start."""

    def progress(run_id: str, sim_s: float, rtf: float) -> None:
        SIM_TIME.labels(run_id).set(sim_s)
        RTF.labels(run_id).set(rtf)

    def ended(job_id: str, kind: JobKind, state: str) -> None:
        if kind == JobKind.RUN:
            RUNS.labels(state).inc()
            for gauge in (SIM_TIME, RTF):
                with suppress(KeyError):  # ended before any progress
                    gauge.remove(job_id)
        count_sweeps(jobs)

    jobs.on_progress, jobs.on_ended = progress, ended
    jobs.on_admitted = lambda kind: count_sweeps(jobs)

    def point_done(state: str) -> None:
        SWEEP_POINTS.labels(state).inc()
        count_sweeps(jobs)

    jobs.on_point_done = point_done
    SLOTS_BUSY.set_function(jobs.slots.in_use)  # read at each scrape: runs and sweep points alike
    for state in (RunState.COMPLETED, RunState.FAILED, RunState.TIMED_OUT):
        SWEEP_POINTS.labels(state)
    for reason in ("token", "origin", "body_size", "json_depth", "max_queued"):
        REFUSED.labels(reason)
    count_sweeps(jobs)


def count_sweeps(jobs: JobService) -> None:
    """The gauges of work waiting: active runs and sweeps, and points left (read from the store:
    called when a job is admitted or ends, and when sweeps are listed)."""
    active = jobs.store.list(JobKind.SWEEP, ACTIVE)
    SWEEPS_ACTIVE.set(len(active))
    ACTIVE_RUNS.set(len(jobs.store.list(JobKind.RUN, ACTIVE)))
    POINTS_REMAINING.set(sum(d["progress"]["points_total"] - d["progress"]["points_done"]
                             for s in active if (d := jobs.describe(s["job_id"])) is not None))
