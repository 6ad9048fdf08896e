"""A small client of the coordinator's REST API: submit a run, follow it, print its KPIs.

Used by ``make up`` (``cosim5g submit --follow``) against the coordinator started by compose.
Every call but ``/healthz`` carries the API token: ``COSIM5G_TOKEN``, else the token file
(``COSIM5G_TOKEN_FILE``, default ``results/auth/api-token``; see ``interfaces.auth``).
"""

from __future__ import annotations

import json
import sys
import time
import urllib.error
import urllib.request
from collections.abc import Callable
from typing import Any

from coordinator.run_state import ACTIVE, RunState
from fabric.settings import settings
from interfaces.auth import DEFAULT_TOKEN_FILE, TOKEN_ENV, TOKEN_FILE_ENV, client_token


class ApiError(RuntimeError):
    pass


def request(base: str, method: str, path: str, body: Any = None, timeout_s: float = 30.0,
            token: str | None = None) -> tuple[int, Any]:
    """HTTP status and decoded JSON body (text, or bytes for files) of one API call; raises ApiError
    if unreachable. ``token``: None finds it (``interfaces.auth.client_token``), "" sends none."""
    data = None if body is None else json.dumps(body).encode()
    headers = {"content-type": "application/json"}
    token = client_token() if token is None else token
    if token:
        headers["authorization"] = f"Bearer {token}"
    req = urllib.request.Request(base.rstrip("/") + path, data=data, method=method, headers=headers)
    try:
        with urllib.request.urlopen(req, timeout=timeout_s) as resp:
            status, ctype, body = resp.status, resp.headers.get_content_type(), resp.read()
    except urllib.error.HTTPError as err:
        status, ctype, body = err.code, err.headers.get_content_type(), err.read()
    except (urllib.error.URLError, OSError) as err:
        raise ApiError(f"coordinator at {base} is not reachable: {err}") from None
    if not (ctype.startswith("text/") or ctype.endswith("json")):
        return status, body  # a figure or a table: bytes
    raw = body.decode()
    try:
        return status, json.loads(raw)
    except json.JSONDecodeError:
        return status, raw


def call(base: str, method: str, path: str, body: Any = None, timeout_s: float = 30.0,
         token: str | None = None) -> Any:
    """The decoded body of a successful call; ApiError with the server's explanation otherwise."""
    status, payload = request(base, method, path, body, timeout_s, token)
    if status < 400:
        return payload
    if status == 401:
        raise ApiError(f"{method} {path}: HTTP 401: the coordinator at {base} refused the API token "
                       f"({_token_source(token)}). Set {TOKEN_ENV} to its token, or point --token-file "
                       f"(or {TOKEN_FILE_ENV}) at the token file it wrote at its first start "
                       f"(default {DEFAULT_TOKEN_FILE}, readable by its owner only)")
    detail = payload.get("detail", payload) if isinstance(payload, dict) else payload
    if isinstance(detail, list):
        detail = "; ".join(f"{d.get('field', d.get('loc'))}: {d.get('message', d.get('msg'))}" for d in detail)
    raise ApiError(f"{method} {path}: HTTP {status}: {detail}")


def _token_source(token: str | None) -> str:
    if token:
        return "the token given was wrong"
    if token == "":
        return "no token was sent"
    given = settings()
    if given.token:
        return f"the token in {TOKEN_ENV} was wrong"
    path = str(given.token_file or DEFAULT_TOKEN_FILE)
    if client_token() is None:
        return f"none sent: {TOKEN_ENV} is not set and {path} cannot be read"
    return f"the token in {path} was wrong"


def wait_healthy(base: str, timeout_s: float) -> None:
    deadline = time.monotonic() + timeout_s
    last = ""
    while time.monotonic() < deadline:
        try:
            if call(base, "GET", "/healthz", timeout_s=5).get("status") == "ok":
                return
        except ApiError as exc:
            last = str(exc)
        time.sleep(1.0)
    raise ApiError(f"coordinator not healthy within {timeout_s:.0f} s ({last})")


def _follow(base: str, path: str, state_key: str, line: Callable[[dict[str, Any]], str], stream: Any,
            poll_s: float, token: str | None) -> dict[str, Any]:
    """Poll ``path`` until its ``state_key`` leaves pending/running, showing ``line`` of it."""
    while True:
        rec = call(base, "GET", path, token=token)
        if rec[state_key] not in ACTIVE:
            stream.write("\n")
            return dict(rec)
        stream.write("\r" + line(rec))
        stream.flush()
        time.sleep(poll_s)


def follow(base: str, run_id: str, stream: Any = sys.stderr, poll_s: float = 1.0,
           token: str | None = None) -> dict[str, Any]:
    """Poll a run until it ends, showing simulated time and real-time factor; the run record."""
    def line(run: dict[str, Any]) -> str:
        sim = run.get("sim_time_s") or 0.0
        total = run["config"]["duration_s"]
        rtf = run.get("real_time_factor") or 0.0
        return f"{run_id}: {run['status']:<8} sim {sim:7.2f}/{total:.2f} s  rtf {rtf:5.2f}"

    return _follow(base, f"/runs/{run_id}", "status", line, stream, poll_s, token)


def follow_sweep(base: str, sweep_id: str, stream: Any = sys.stderr, poll_s: float = 2.0,
                 token: str | None = None) -> dict[str, Any]:
    """Poll a sweep until it ends, showing points done / total and the points running; the sweep."""
    def line(s: dict[str, Any]) -> str:
        prog = s["progress"]
        running = ", ".join(" ".join(f"{k}={v}" for k, v in p["values"].items()) + f" sim {p.get('sim_time_s') or 0:.1f} s"
                            for p in s["points"] if p["state"] == RunState.RUNNING)
        eta = f"ETA {prog['eta_s'] / 60:.1f} min" if prog.get("eta_s") is not None else ""
        return (f"{sweep_id}: {s['state']:<8} {prog['points_done']}/{prog['points_total']} points "
                f"{running} {eta}\x1b[K")

    return _follow(base, f"/sweeps/{sweep_id}", "state", line, stream, poll_s, token)
