"""The site around the API: health, Prometheus metrics, the browser's login, the OpenAPI
document and its Swagger UI (served from this host: it works offline), the results index."""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import Annotated, Any

from fastapi import APIRouter, HTTPException, Query
from fastapi.openapi.docs import get_swagger_ui_html
from fastapi.responses import (
    FileResponse,
    HTMLResponse,
    JSONResponse,
    PlainTextResponse,
    RedirectResponse,
)
from prometheus_client import CONTENT_TYPE_LATEST, generate_latest
from pydantic import BaseModel

from experiments.job_store import JobKind
from experiments.jobs import JobService
from interfaces.auth import token_matches
from interfaces.guard import COOKIE
from interfaces.pages import index_page
from interfaces.routes.runs import run_detail

# The Swagger UI's files, as the fastapi-offline package ships them.
DOCS_ASSETS = {"swagger-ui-bundle.js": "text/javascript", "swagger-ui.css": "text/css"}


class Health(BaseModel):
    status: str


def _assets_dir() -> Path:
    import fastapi_offline

    return Path(fastapi_offline.__file__).parent / "static"


def site_router(jobs: JobService, token: str, refused: str, openapi: Callable[[], dict[str, Any]],
                on_refused: Callable[[str], None]) -> APIRouter:
    """``refused``: the 401's detail; ``openapi()``: the app's OpenAPI document."""
    router = APIRouter(tags=["site"])

    @router.get("/healthz")
    def healthz() -> Health:
        return Health(status="ok")

    @router.get("/metrics", response_class=PlainTextResponse)
    def metrics() -> PlainTextResponse:
        return PlainTextResponse(generate_latest().decode(), media_type=CONTENT_TYPE_LATEST)

    @router.get("/login", status_code=303, response_class=RedirectResponse,
                responses={303: {"description": "token accepted: a cookie is set, on to `next`"}})
    def login(token_: Annotated[str, Query(alias="token", description="the API token")],
              next_: Annotated[str, Query(alias="next", description="a page of this API to go to")] = "/",
              ) -> RedirectResponse:
        """For a browser: the results pages then work with a cookie instead of a header."""
        if not token_matches(token_, token):  # the guard may have passed on a header or cookie
            on_refused("token")
            raise HTTPException(401, refused, headers={"WWW-Authenticate": "Bearer"})
        # Only a path of this site: "//host" or a URL would make the login an open redirect.
        local = next_.startswith("/") and not next_.startswith("//") and "\\" not in next_
        resp = RedirectResponse(next_ if local else "/", status_code=303)
        resp.set_cookie(COOKIE, token_, httponly=True, samesite="strict", path="/")
        return resp

    @router.get("/openapi.json", include_in_schema=False)
    def openapi_json() -> JSONResponse:
        return JSONResponse(openapi())

    @router.get("/docs", include_in_schema=False)
    def docs() -> HTMLResponse:
        return get_swagger_ui_html(openapi_url="/openapi.json", title="cosim5g coordinator",
                                   swagger_js_url="/docs/swagger-ui-bundle.js",
                                   swagger_css_url="/docs/swagger-ui.css", swagger_favicon_url="")

    @router.get("/docs/{name}", include_in_schema=False)
    def docs_asset(name: str) -> FileResponse:
        if name not in DOCS_ASSETS:  # by exact name: never a path
            raise HTTPException(404, f"no {name!r}; files: {', '.join(DOCS_ASSETS)}")
        return FileResponse(_assets_dir() / name, media_type=DOCS_ASSETS[name])

    @router.get("/", response_class=HTMLResponse)
    def index() -> HTMLResponse:
        sweeps = [jobs.describe(s["job_id"]) for s in jobs.store.list(JobKind.SWEEP)]
        runs = [run_detail(r).model_dump() for r in jobs.store.list(JobKind.RUN, limit=20)]
        return HTMLResponse(index_page([s for s in sweeps if s is not None], runs))

    return router
