"""The coordinator's REST API: start runs, follow them, read their KPIs; Prometheus ``/metrics``.

Runs execute one at a time on a worker thread (a run already uses every core of a small host).
Request bodies are validated by the same scenario schema as the CLI, and invalid ones get a 422
listing each field and what is allowed.

Every route but ``/healthz`` needs the bearer token (``interfaces.auth``): the check is a
dependency of the whole app, so routes added later are covered without a word. A browser gets
a cookie from ``/login?token=...`` instead. Scenario and sweep names are looked up in the
shipped lists, never used as paths; ``ApiLimits`` bounds what one request may ask for (422
naming the limit) and how much work may wait (429).
"""

from __future__ import annotations

import json
import logging
import os
import queue
import threading
from collections.abc import AsyncIterator, Callable, Mapping
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Annotated, Any

from fastapi import Depends, FastAPI, HTTPException, Query, Request
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import HTMLResponse, JSONResponse, PlainTextResponse, RedirectResponse
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer
from prometheus_client import CONTENT_TYPE_LATEST, Counter, Gauge, generate_latest
from pydantic import BaseModel, ConfigDict, Field, ValidationError

from coordinator.conductor import Progress
from coordinator.run import RunResult, execute_run, new_run_id, salvage_run
from experiments.executors import Executor
from experiments.service import SweepService
from experiments.spec import SweepError, SweepSpec, base_path, overrides
from interfaces.api_sweeps import add_sweep_routes
from interfaces.auth import token_matches
from interfaces.store import ORPHAN_REASON, RunStore
from scenario.schema import Scenario, ScenarioError, load_scenario, parse_scenario, shipped_names

log = logging.getLogger(__name__)

RUNS = Counter("cosim_coordinator_runs_total", "Runs finished, by final state", ["status"])
ACTIVE = Gauge("cosim_coordinator_runs_active", "Runs pending or running")
SIM_TIME = Gauge("cosim_coordinator_run_sim_time_seconds", "Simulated time reached by the current run")
RTF = Gauge("cosim_coordinator_run_real_time_factor", "Real-time factor of the current run")
REFUSED = Counter("cosim_coordinator_requests_refused_total", "Requests refused by a limit or for the token",
                  ["reason"])

# Routes anyone may call: liveness only (the compose healthcheck and load balancers know no token).
PUBLIC_PATHS = frozenset({"/healthz"})
COOKIE = "cosim5g_token"
BEARER = HTTPBearer(auto_error=False, scheme_name="token",
                    description="the coordinator's API token: results/auth/api-token on its host, or COSIM5G_TOKEN")


class ApiLimits(BaseModel):
    """What one request may ask of this coordinator. Each limit is set by a ``cosim5g serve``
    flag or, failing that, by its environment variable (``COSIM5G_`` + the name in capitals)."""

    model_config = ConfigDict(extra="forbid", frozen=True)
    max_duration_s: float = Field(default=3600.0, gt=0, description="longest simulated duration_s of a run or "
                                  "sweep point, s")
    max_run_timeout_s: float = Field(default=21600.0, gt=0, description="largest watchdog.run_timeout_s (wall "
                                     "clock) of a run or sweep point, s")
    max_sweep_points: int = Field(default=1000, ge=1, description="most points (grid combinations x seeds, "
                                  "repeat_until's extra seeds included) in one sweep")
    max_queued: int = Field(default=32, ge=1, description="most runs and sweeps pending or running at once")

    @classmethod
    def from_env(cls, environ: Mapping[str, str] | None = None, **given: Any) -> ApiLimits:
        """Limits from ``given`` (None = not given), else ``COSIM5G_<NAME>``, else the default;
        ValueError naming the flag and variable of a bad value."""
        environ = os.environ if environ is None else environ
        values: dict[str, Any] = {}
        for name in cls.model_fields:
            if given.get(name) is not None:
                values[name] = given[name]
            elif (env := environ.get(f"COSIM5G_{name.upper()}")) is not None:
                values[name] = env
        try:
            return cls(**values)
        except ValidationError as exc:
            raise ValueError("; ".join(
                f"{limit_source(str(e['loc'][0]))}: {e['msg']} (given {e['input']!r})" for e in exc.errors())) from None


def limit_source(name: str) -> str:
    """How a limit is set, for messages: ``max_queued (--max-queued, COSIM5G_MAX_QUEUED)``."""
    return f"{name} (--{name.replace('_', '-')}, COSIM5G_{name.upper()})"


class TooMuchWork(Exception):
    """The queue is full: answered with 429."""


class RunRequest(BaseModel):
    """Start a run from a shipped scenario and/or an inline scenario, plus overrides."""

    model_config = ConfigDict(extra="forbid")
    scenario: str | None = Field(default=None, description="name of a file in configs/scenarios/")
    config: dict[str, Any] | None = Field(default=None, description="inline scenario fields")
    overrides: list[str] = Field(default_factory=list, description="field.path=value assignments")


class Coordinator:
    """Owns the store, the run queue and the worker thread."""

    def __init__(self, results_root: Path, db_path: Path, scenarios_dir: Path,
                 limits: ApiLimits | None = None, execute: Callable[..., RunResult] = execute_run) -> None:
        self.results_root = results_root
        self.execute = execute
        self.scenarios_dir = scenarios_dir
        self.limits = limits or ApiLimits()
        self.admit = threading.Lock()  # the queue check and the enqueue, as one step
        self.queued_elsewhere: Callable[[], int] = lambda: 0  # sweeps pending or running (set by create_app)
        self.store = RunStore(db_path)
        for run_id, results_dir in self.store.reap_orphans():
            try:  # what the run's federates streamed before the coordinator died is kept
                salvage_run(Path(results_dir), ORPHAN_REASON)
            except OSError as exc:
                log.warning("run %s: could not close its records in %s: %s", run_id, results_dir, exc)
        self.queue: queue.SimpleQueue[tuple[str, Any] | None] = queue.SimpleQueue()
        self.busy = threading.Lock()  # held while a simulation runs (a run here, or a sweep point)
        self.cancels: dict[str, threading.Event] = {}
        self.worker = threading.Thread(target=self._work, daemon=True, name="runs")
        self.worker.start()

    def queued(self) -> int:
        """Runs and sweeps pending or running."""
        return len(self.cancels) + int(self.queued_elsewhere())

    def check_queue(self) -> None:
        n = self.queued()
        if n >= self.limits.max_queued:
            raise TooMuchWork(f"{n} runs and sweeps are pending or running, the most this coordinator queues: "
                              f"{limit_source('max_queued')} = {self.limits.max_queued}; retry when one has ended")

    def submit(self, req: RunRequest) -> dict[str, Any]:
        if req.scenario is not None:
            known = shipped_names(self.scenarios_dir)
            if req.scenario not in known:  # checked against the list: a name never becomes a path
                raise ScenarioError([("scenario", f"{req.scenario!r} is not one of {known}")])
            sc = load_scenario(self.scenarios_dir / f"{req.scenario}.yaml",
                               [*(f"{k}={v}" for k, v in _flatten(req.config or {})), *req.overrides])
        else:
            sc = parse_scenario(req.config or {}, req.overrides)
        errors = scenario_limit_errors(sc, self.limits)
        if errors:
            raise ScenarioError(errors)
        with self.admit:
            self.check_queue()
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
                    result = self.execute(sc, self.results_root, on_progress=progress, cancel=cancel, run_id=run_id)
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


def scenario_limit_errors(sc: Scenario, limits: ApiLimits) -> list[tuple[str, str]]:
    """(field, message) for each field of ``sc`` beyond this coordinator's limits."""
    errors = []
    if sc.duration_s > limits.max_duration_s:
        errors.append(("duration_s", f"{sc.duration_s:g} s is more than this coordinator allows: "
                                     f"{limit_source('max_duration_s')} = {limits.max_duration_s:g} s"))
    if sc.watchdog.run_timeout_s > limits.max_run_timeout_s:
        errors.append(("watchdog.run_timeout_s", f"{sc.watchdog.run_timeout_s:g} s is more than this coordinator "
                       f"allows: {limit_source('max_run_timeout_s')} = {limits.max_run_timeout_s:g} s"))
    return errors


def sweep_limit_errors(spec: SweepSpec, scenarios_dir: Path, limits: ApiLimits) -> list[tuple[str, str]]:
    """(field, message) for a point beyond the run limits (the number of points is refused
    earlier, before any point is validated: ``parse_spec``'s ``max_points``)."""
    errors = []
    # Only duration_s and watchdog.run_timeout_s matter here, and each is either fixed (base and
    # set), one grid axis, or set by variants: checking the base, each value of that axis and
    # each variant's value covers every point.
    base = load_scenario(base_path(spec.base, scenarios_dir, allow_paths=False), overrides(spec.set))
    grid = spec.grid_values()
    for path, field, limit in (("duration_s", "max_duration_s", limits.max_duration_s),
                               ("watchdog.run_timeout_s", "max_run_timeout_s", limits.max_run_timeout_s)):
        fixed = base.duration_s if path == "duration_s" else base.watchdog.run_timeout_s
        candidates = ([(f"grid.{path}", v) for v in grid[path]] if path in grid
                      else [(f"set.{path}" if path in spec.set else f"base.{path}", fixed)])
        candidates += [(f"variants.{name}.{path}", fields[path])
                       for name, fields in spec.variants.items() if path in fields]
        for where, value in candidates:
            if float(value) > limit:
                errors.append((where, f"{float(value):g} s is more than this coordinator allows: "
                                      f"{limit_source(field)} = {limit:g} s"))
                break
    return errors


def document_refusals(schema: dict[str, Any]) -> dict[str, Any]:
    """The OpenAPI schema as the app answers: /healthz needs no token (the app-wide dependency
    marks every route), every other operation may answer 401, the two that queue work 429, and a
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
               sweeps_dir: Path | None = None, sweep_jobs: int = 1, *, token: str,
               limits: ApiLimits | None = None,
               token_hint: str = "the coordinator's COSIM5G_TOKEN or the content of its token file",
               execute: Callable[..., RunResult] = execute_run,
               make_sweep_executor: Callable[[], Executor] | None = None) -> FastAPI:
    """The app; ``token`` is the bearer token every route but /healthz needs (``token_hint``
    tells a refused client where to find it). ``execute`` runs one run and
    ``make_sweep_executor`` makes a sweep's executor (defaults: the real ones)."""
    coord = Coordinator(results_root, db_path, scenarios_dir, limits, execute)
    limits = coord.limits
    sweeps_root = sweeps_root or results_root.parent / "sweeps"
    sweeps_dir = sweeps_dir or scenarios_dir.parent / "sweeps"
    # Single runs and sweep points share the host: one of them at a time.
    sweeps = SweepService(db_path, sweeps_root, scenarios_dir, jobs=sweep_jobs, busy=coord.busy,
                          make_executor=make_sweep_executor)
    coord.queued_elsewhere = sweeps.queued

    @asynccontextmanager
    async def lifespan(_: FastAPI) -> AsyncIterator[None]:
        yield
        sweeps.close()
        coord.close()

    refused = (f"missing or wrong API token: send the header 'Authorization: Bearer <token>'; the token is "
               f"{token_hint}")

    def require_token(request: Request,
                      credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(BEARER)]) -> None:
        if request.url.path in PUBLIC_PATHS:
            return
        given = credentials.credentials if credentials is not None else request.cookies.get(COOKIE)
        if request.url.path == "/login" and given is None:
            given = request.query_params.get("token")
        if given is None or not token_matches(given, token):
            REFUSED.labels("token").inc()
            raise HTTPException(401, refused, headers={"WWW-Authenticate": "Bearer"})

    # The framework's own /openapi.json and /docs would bypass app dependencies: they are added
    # below as ordinary (protected) routes instead.
    app = FastAPI(title="cosim5g coordinator", version="0.1.0", lifespan=lifespan,
                  dependencies=[Depends(require_token)], openapi_url=None, docs_url=None, redoc_url=None)
    app.state.coordinator = coord
    app.state.sweeps = sweeps
    app.state.limits = limits

    def check_spec(spec: SweepSpec, service: SweepService) -> None:
        errors = sweep_limit_errors(spec, scenarios_dir, limits)
        if errors:
            raise SweepError(errors)
        coord.check_queue()

    add_sweep_routes(app, sweeps, sweeps_dir, scenarios_dir, check_spec=check_spec,
                     recent_runs=lambda: coord.store.list(limit=20),
                     max_points=(limits.max_sweep_points, limit_source("max_sweep_points")))

    @app.exception_handler(ScenarioError)
    async def invalid_scenario(_: Any, exc: ScenarioError) -> JSONResponse:
        return JSONResponse(status_code=422, content={"detail": [{"field": f, "message": m} for f, m in exc.errors]})

    @app.exception_handler(TooMuchWork)
    async def too_much_work(_: Any, exc: TooMuchWork) -> JSONResponse:
        REFUSED.labels("max_queued").inc()
        return JSONResponse(status_code=429, content={"detail": str(exc)}, headers={"Retry-After": "60"})

    def openapi_schema() -> dict[str, Any]:
        if app.openapi_schema is None:
            app.openapi_schema = document_refusals(FastAPI.openapi(app))
        return app.openapi_schema

    app.openapi = openapi_schema  # type: ignore[method-assign]

    @app.get("/openapi.json", include_in_schema=False)
    def openapi() -> JSONResponse:
        return JSONResponse(app.openapi())

    @app.get("/docs", include_in_schema=False)
    def docs() -> HTMLResponse:
        return get_swagger_ui_html(openapi_url="/openapi.json", title="cosim5g coordinator")

    @app.get("/login", status_code=303, response_class=RedirectResponse,
             responses={303: {"description": "token accepted: a cookie is set, on to `next`"}})
    def login(token_: Annotated[str, Query(alias="token", description="the API token")],
              next_: Annotated[str, Query(alias="next", description="a page of this API to go to")] = "/",
              ) -> RedirectResponse:
        """For a browser: the results pages then work with a cookie instead of a header."""
        if not token_matches(token_, token):  # the check above may have passed on a header or cookie
            REFUSED.labels("token").inc()
            raise HTTPException(401, refused, headers={"WWW-Authenticate": "Bearer"})
        # Only a path of this site: "//host" or a URL would make the login an open redirect.
        local = next_.startswith("/") and not next_.startswith("//") and "\\" not in next_
        resp = RedirectResponse(next_ if local else "/", status_code=303)
        resp.set_cookie(COOKIE, token_, httponly=True, samesite="strict", path="/")
        return resp

    @app.get("/healthz")
    def healthz() -> dict[str, str]:
        return {"status": "ok"}

    @app.get("/metrics")
    def metrics() -> PlainTextResponse:
        return PlainTextResponse(generate_latest().decode(), media_type=CONTENT_TYPE_LATEST)

    @app.get("/scenarios")
    def scenarios() -> list[str]:
        return shipped_names(scenarios_dir)

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
