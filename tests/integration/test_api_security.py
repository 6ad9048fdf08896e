"""The API's access rules: the bearer token on every route but /healthz, names that never become
paths, and the limits on what a request may ask for (each refusal naming its limit).

The real app is served over HTTP by uvicorn on a thread. Runs never simulate here: the app gets a
stand-in ``execute`` that holds each run until it is cancelled, so that queued work stays queued
while the limits are probed."""

from __future__ import annotations

import http.client
import json
import os
import re
import stat
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any
from urllib.parse import urlencode

import pytest
import uvicorn
from fastapi import FastAPI
from fastapi.routing import APIRoute

from coordinator.run import RunResult
from experiments.point_runs import PointTask
from fabric.settings import settings
from interfaces.api import create_app
from interfaces.auth import TokenError, listen_sockets, server_token, token_matches
from interfaces.guard import Guard
from scenario.schema import Scenario

pytestmark = pytest.mark.integration
ROOT = Path(__file__).parents[2]
TOKEN = "test-token-0123456789abcdef"
AUTH = {"Authorization": f"Bearer {TOKEN}"}
# The scenarios the API offers: the shipped ones, by name.
SHIPPED = sorted(p.stem for p in (ROOT / "configs" / "scenarios").glob("*.yaml"))


class HeldRuns:
    """Stands in for ``execute_run``: a run is 'running' until it is cancelled."""

    def __init__(self) -> None:
        self.started: list[str] = []

    def __call__(self, sc: Scenario, results_root: Path, on_progress: Any = None,
                 cancel: threading.Event | None = None, run_id: str | None = None) -> RunResult:
        assert cancel is not None and run_id is not None
        self.started.append(run_id)
        cancel.wait(60)
        return RunResult(run_id, "cancelled", results_root / run_id, {}, "cancelled by the test")


class NoPoints:
    """A sweep executor that runs nothing."""

    name = "none"

    def run(self, tasks: list[PointTask], on_start: Any, on_done: Any, cancel: threading.Event) -> None:
        del tasks, on_start, on_done, cancel


def make_app(tmp_path: Path, **limits: Any) -> tuple[Guard, HeldRuns]:
    held = HeldRuns()
    app = create_app(tmp_path / "runs", tmp_path / "store.db", ROOT / "configs" / "scenarios",
                     tmp_path / "sweeps", ROOT / "configs" / "sweeps", token=TOKEN,
                     limits=settings(**limits), execute=held,
                     make_sweep_executor=lambda slots: NoPoints())
    return app, held


class Reply:
    def __init__(self, status: int, headers: http.client.HTTPMessage, body: bytes) -> None:
        self.status_code, self.headers, self.body = status, headers, body
        self.text = body.decode(errors="replace")

    def json(self) -> Any:
        return json.loads(self.body)


class Client:
    """Plain HTTP to a served app: no redirect is followed, the cookie is kept like a browser's."""

    def __init__(self, app: Guard, port: int) -> None:
        self.app, self.port = app, port
        self.cookie: str | None = None

    def request(self, method: str, path: str, headers: dict[str, str] | None = None, json_body: Any = None,
                params: dict[str, str] | None = None) -> Reply:
        conn = http.client.HTTPConnection("127.0.0.1", self.port, timeout=30)
        hdrs = dict(headers or {})
        body = None
        if json_body is not None:
            body = json.dumps(json_body).encode()
            hdrs["content-type"] = "application/json"
        if self.cookie:
            hdrs["cookie"] = self.cookie
        try:
            conn.request(method, path + (f"?{urlencode(params)}" if params else ""), body=body, headers=hdrs)
            resp = conn.getresponse()
            reply = Reply(resp.status, resp.headers, resp.read())
        finally:
            conn.close()
        if (set_cookie := reply.headers.get("set-cookie")) is not None:
            self.cookie = set_cookie.split(";", 1)[0]
        return reply

    def get(self, path: str, **kw: Any) -> Reply:
        return self.request("GET", path, **kw)

    def post(self, path: str, json: Any = None, **kw: Any) -> Reply:
        return self.request("POST", path, json_body=json, **kw)


@contextmanager
def serving(app: Guard) -> Iterator[Client]:
    """The app behind uvicorn on a loopback port, lifespan included."""
    [sock] = listen_sockets(["127.0.0.1"], 0)
    server = uvicorn.Server(uvicorn.Config(app, log_level="warning"))
    thread = threading.Thread(target=server.run, kwargs={"sockets": [sock]}, daemon=True)
    thread.start()
    deadline = time.monotonic() + 30
    while not server.started:
        assert thread.is_alive() and time.monotonic() < deadline, "uvicorn did not start"
        time.sleep(0.05)
    try:
        yield Client(app, sock.getsockname()[1])
    finally:
        server.should_exit = True
        thread.join(60)
        sock.close()


@pytest.fixture
def client(tmp_path: Path) -> Iterator[Client]:
    app, _ = make_app(tmp_path)
    with serving(app) as c:
        yield c


def concrete(path: str) -> str:
    """A route's path with every {parameter} filled in."""
    return re.sub(r"\{[^}]+\}", "x", path)


def routes(app: FastAPI) -> list[Any]:
    """Every route of the app, those of its included routers too."""
    out = []
    for route in app.routes:
        inner = getattr(route, "original_router", None)
        out += routes(inner) if inner is not None else [route]
    return out


def test_every_route_but_healthz_wants_the_token(client: Client) -> None:
    app = client.app.app
    assert isinstance(app, FastAPI)
    checked = 0
    for route in routes(app):  # whatever routes exist, now or added later
        path = getattr(route, "path", None)
        methods = getattr(route, "methods", None) or {"GET"}
        if path is None:
            continue
        for method in sorted(methods - {"HEAD", "OPTIONS"}):
            url = concrete(path)
            for headers in ({}, {"Authorization": "Bearer wrong-token-0123456789"},
                            {"Authorization": f"Basic {TOKEN}"}):
                r = client.request(method, url, headers=headers)
                if path == "/healthz":
                    assert r.status_code == 200
                    continue
                assert r.status_code == 401, (method, url, headers, r.status_code, r.text)
                assert r.headers["www-authenticate"] == "Bearer"
                assert "Authorization: Bearer" in r.json()["detail"]
                checked += 1
    # The run and sweep routes, the pages, /metrics and the schema are all among them.
    assert checked >= 3 * 15
    paths = {getattr(r, "path", None) for r in routes(app)}
    assert {"/runs", "/sweeps", "/metrics", "/openapi.json", "/", "/scenarios"} <= paths


def test_with_the_token_routes_answer(client: Client) -> None:
    assert client.get("/scenarios", headers=AUTH).json() == SHIPPED
    assert client.get("/runs", headers=AUTH).json() == []
    assert client.get("/metrics", headers=AUTH).status_code == 200
    schema = client.get("/openapi.json", headers=AUTH).json()
    # The schema says which operations need the token, and that /healthz does not.
    assert schema["components"]["securitySchemes"]["token"] == {
        "type": "http", "scheme": "bearer", "description": schema["components"]["securitySchemes"]["token"]["description"]}
    assert "security" not in schema["paths"]["/healthz"]["get"]
    assert schema["paths"]["/runs"]["post"]["security"] == [{"token": []}]


def test_a_browser_logs_in_once_and_then_uses_a_cookie(client: Client) -> None:
    assert client.get("/login", params={"token": "wrong-token-0123456789"}).status_code == 401
    assert client.cookie is None
    r = client.get("/login", params={"token": TOKEN})
    assert r.status_code == 303 and r.headers["location"] == "/"
    cookie = r.headers["set-cookie"].lower()
    assert "httponly" in cookie and "samesite=strict" in cookie
    for target, landing in (("/sweeps", "/sweeps"), ("//elsewhere.example/x", "/"), ("https://elsewhere.example", "/")):
        r = client.get("/login", params={"token": TOKEN, "next": target})
        assert r.status_code == 303 and r.headers["location"] == landing
    page = client.get("/", headers={"accept": "text/html"})
    assert page.status_code == 200 and "<html" in page.text
    # A stale cookie (a token since replaced) does not keep a browser from logging in again.
    client.cookie = "cosim5g_token=stale-token-0123456789abcdef"
    assert client.get("/runs").status_code == 401
    assert client.get("/login", params={"token": TOKEN}).status_code == 303
    assert client.get("/runs").status_code == 200
    client.cookie = None
    assert client.get("/", headers={"accept": "text/html"}).status_code == 401


@pytest.mark.parametrize("name", ["../../etc/x", "/etc/passwd", "smoke/../smoke", "..", "smoke.yaml", ""])
def test_names_from_a_request_are_checked_against_the_shipped_lists(client: Client, name: str) -> None:
    r = client.post("/runs", json={"scenario": name}, headers=AUTH)
    assert r.status_code == 422
    assert r.json()["detail"] == [{"field": "scenario",
                                   "message": f"{name!r} is not one of {SHIPPED}"}]
    r = client.post("/sweeps", json={"spec": name}, headers=AUTH)
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "spec"
    spec = {"name": "s", "base": name, "grid": {"loops": [2]}}
    r = client.post("/sweeps", json={"spec": spec}, headers=AUTH)
    assert r.status_code == 422 and r.json()["detail"][0]["field"] == "base"


def test_run_limits_are_answered_with_422_naming_the_limit(tmp_path: Path) -> None:
    app, held = make_app(tmp_path, max_duration_s=20, max_run_timeout_s=600)
    with serving(app) as c:
        r = c.post("/runs", json={"scenario": "smoke", "config": {"duration_s": 21},
                                  "overrides": ["watchdog.run_timeout_s=600"]}, headers=AUTH)
        assert r.status_code == 422
        [err] = r.json()["detail"]
        assert err["field"] == "duration_s"
        assert "max_duration_s" in err["message"] and "20 s" in err["message"] and "--max-duration-s" in err["message"]
        r = c.post("/runs", json={"scenario": "smoke", "overrides": ["watchdog.run_timeout_s=601"]}, headers=AUTH)
        assert r.status_code == 422
        [err] = r.json()["detail"]
        assert err["field"] == "watchdog.run_timeout_s" and "max_run_timeout_s" in err["message"]
        # The scenario default (3600 s) is beyond this coordinator's limit too: named as well.
        r = c.post("/runs", json={"scenario": "smoke", "config": {"duration_s": 20}}, headers=AUTH)
        assert r.status_code == 422 and r.json()["detail"][0]["field"] == "watchdog.run_timeout_s"
        ok = {"scenario": "smoke", "config": {"duration_s": 20}, "overrides": ["watchdog.run_timeout_s=600"]}
        r = c.post("/runs", json=ok, headers=AUTH)
        assert r.status_code == 201, r.text
    assert held.started == [r.json()["run_id"]]


def test_sweep_limits_are_answered_with_422_naming_the_limit(tmp_path: Path) -> None:
    app, held = make_app(tmp_path, max_sweep_points=4, max_duration_s=30)
    spec = {"name": "s", "base": "baseline", "grid": {"loops": [2, 4, 6]}, "seeds": 2,
            "set": {"duration_s": 5, "detailed_loops": 0}}
    with serving(app) as c:
        r = c.post("/sweeps", json={"spec": spec}, headers=AUTH)
        assert r.status_code == 422
        [err] = r.json()["detail"]
        assert err["field"] == "grid" and "6 points" in err["message"] and "max_sweep_points" in err["message"]
        # repeat_until's extra seeds count: 1 combination x up to 5 seeds.
        r = c.post("/sweeps", json={"spec": {**spec, "grid": {"loops": [2]},
                                             "repeat_until": {"min_tasks": 10, "max_seeds": 5}}}, headers=AUTH)
        assert r.status_code == 422 and "max_sweep_points" in r.json()["detail"][0]["message"]
        r = c.post("/sweeps", json={"spec": {**spec, "seeds": 1, "set": {"detailed_loops": 0},
                                             "grid": {"loops": [2], "duration_s": [10, 40]}}}, headers=AUTH)
        assert r.status_code == 422
        [err] = r.json()["detail"]
        assert err["field"] == "grid.duration_s[1]" and "40 s" in err["message"] and "max_duration_s" in err["message"]
        r = c.post("/sweeps", json={"spec": {**spec, "seeds": 1, "set": {"duration_s": 31, "detailed_loops": 0}}},
                   headers=AUTH)
        assert r.status_code == 422 and r.json()["detail"][0]["field"] == "set.duration_s"
        # A variant's own duration is held to the limit too.
        r = c.post("/sweeps", json={"spec": {**spec, "seeds": 1, "set": {"detailed_loops": 0}, "grid": {"loops": [2]},
                                             "variants": {"short": {"duration_s": 5}, "long": {"duration_s": 45}}}},
                   headers=AUTH)
        assert r.status_code == 422
        [err] = r.json()["detail"]
        assert err["field"] == "variants.long.duration_s" and "45 s" in err["message"]
        # Every resolved point is held to the limits, however its value is set: a whole section
        # as an axis value, or a scale that multiplies an allowed value past the limit.
        r = c.post("/sweeps", json={"spec": {**spec, "seeds": 1, "grid": {
            "loops": [2], "watchdog": [{"run_timeout_s": 1e6}]}}}, headers=AUTH)
        assert r.status_code == 422 and r.json()["detail"][0]["field"] == "grid.watchdog[0]", r.text
        r = c.post("/sweeps", json={"spec": {**spec, "seeds": 1, "set": {"detailed_loops": 0},
                                             "grid": {"duration_s": [20], "loops": [2, 3]},
                                             "scale": {"duration_s": "loops"}}}, headers=AUTH)
        assert r.status_code == 422 and "40 s" in r.json()["detail"][0]["message"], r.text
        r = c.post("/sweeps", json={"spec": {**spec, "seeds": 1}}, headers=AUTH)
        assert r.status_code == 201, r.text
    assert held.started == []


def test_queued_work_beyond_the_limit_gets_429(tmp_path: Path) -> None:
    app, held = make_app(tmp_path, max_queued=2)
    small = {"scenario": "smoke", "config": {"duration_s": 2}}
    with serving(app) as c:
        first = c.post("/runs", json=small, headers=AUTH)
        second = c.post("/runs", json=small, headers=AUTH)
        assert first.status_code == second.status_code == 201
        r = c.post("/runs", json=small, headers=AUTH)
        assert r.status_code == 429
        assert "max_queued" in r.json()["detail"] and "2 runs and sweeps" in r.json()["detail"]
        assert "--max-queued" in r.json()["detail"] and r.headers["retry-after"]
        r = c.post("/sweeps", json={"spec": "quick"}, headers=AUTH)
        assert r.status_code == 429 and "max_queued" in r.json()["detail"]
        # A cancelled run frees its place.
        run_id = first.json()["run_id"]
        assert c.post(f"/runs/{run_id}/cancel", headers=AUTH).status_code == 200
        for _ in range(300):
            if c.get(f"/runs/{run_id}", headers=AUTH).json()["status"] == "cancelled":
                break
            time.sleep(0.1)
        assert c.post("/runs", json=small, headers=AUTH).status_code == 201
        assert 'cosim_coordinator_requests_refused_total{reason="max_queued"}' in c.get(
            "/metrics", headers=AUTH).text


def test_limits_come_from_flags_then_environment_then_defaults(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setenv("COSIM5G_MAX_QUEUED", "3")
    monkeypatch.setenv("COSIM5G_MAX_DURATION_S", "60")
    monkeypatch.delenv("COSIM5G_MAX_SWEEP_POINTS", raising=False)
    limits = settings(max_duration_s=90.0, max_sweep_points=None)
    assert (limits.max_queued, limits.max_duration_s, limits.max_sweep_points) == (3, 90.0, 1000)
    monkeypatch.setenv("COSIM5G_MAX_QUEUED", "0")
    with pytest.raises(ValueError, match=r"max_queued \(COSIM5G_MAX_QUEUED\) = '0'"):
        settings()
    monkeypatch.setenv("COSIM5G_MAX_QUEUED", "4")
    for bad in ("inf", "nan"):
        with pytest.raises(ValueError, match=r"max_duration_s \(COSIM5G_MAX_DURATION_S\) = " + repr(bad)):
            settings(max_duration_s=bad)


def test_the_token_file_is_created_once_and_private(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("COSIM5G_TOKEN", raising=False)
    path = tmp_path / "auth" / "api-token"
    token = server_token(path)
    assert len(token) >= 32 and server_token(path) == token
    assert stat.S_IMODE(path.stat().st_mode) == 0o600
    assert stat.S_IMODE(path.parent.stat().st_mode) == 0o700
    os.chmod(path, 0o644)
    with pytest.raises(TokenError, match="readable by others.*chmod 600"):
        server_token(path)
    monkeypatch.setenv("COSIM5G_TOKEN", "short")
    with pytest.raises(TokenError, match="at least 16"):
        server_token(path)
    monkeypatch.setenv("COSIM5G_TOKEN", TOKEN)
    assert server_token(tmp_path / "unused") == TOKEN and not (tmp_path / "unused").exists()
    # A token file named on purpose is made to hold the token given, for whoever reads it.
    os.chmod(path, 0o600)
    assert server_token(path, keep_env_token=True) == TOKEN
    assert path.read_text().strip() == TOKEN and stat.S_IMODE(path.stat().st_mode) == 0o600
    assert sorted(p.name for p in path.parent.iterdir()) == ["api-token"]
    assert token_matches(TOKEN, TOKEN) and not token_matches(TOKEN[:-1], TOKEN)


def test_paths_no_route_serves_want_the_token_too(client: Client) -> None:
    """The guard answers before routing: without the token, a path or method no route serves says
    nothing of what exists (401, not 404 or 405)."""
    for method, path, served in (("GET", "/nope", 404), ("GET", "/runs/x/y/z", 404), ("DELETE", "/runs", 405),
                                 ("PUT", "/sweeps/x", 405)):
        assert client.request(method, path).status_code == 401
        assert client.request(method, path, headers=AUTH).status_code == served
    # Every route is an API route, documented in the schema.
    assert all(isinstance(r, APIRoute) for r in routes(client.app.app))


def alias_bomb(levels: int = 8) -> str:
    """A 400-byte YAML value whose aliases expand to 9^levels items wherever it is walked."""
    parts = ["a0: &a0 [" + ",".join(["lol"] * 9) + "]"]
    parts += [f"a{i}: &a{i} [" + ",".join([f"*a{i - 1}"] * 9) + "]" for i in range(1, levels)]
    return "{" + ", ".join(parts) + "}"


def test_bad_yaml_in_overrides_is_a_quick_422_naming_the_field(tmp_path: Path) -> None:
    app, held = make_app(tmp_path)
    with serving(app) as c:
        for value, says in [(alias_bomb(), "aliases"), ("[x", "not a YAML value"), ("*undefined", "aliases"),
                            ("!!python/object:os.system ls", "not a YAML value")]:
            t0 = time.monotonic()
            r = c.post("/runs", json={"scenario": "smoke", "overrides": [f"name={value}"]}, headers=AUTH)
            assert r.status_code == 422, (value[:30], r.status_code, r.text[:200])
            [err] = r.json()["detail"]
            assert err["field"] == "name" and says in err["message"]
            assert time.monotonic() - t0 < 5.0  # the bomb took 4 s and 500 MB to answer before
        r = c.post("/runs", json={"scenario": "smoke", "overrides": ["name=" + "x" * 5000]}, headers=AUTH)
        assert r.status_code == 422 and "at most 4096 characters" in r.json()["detail"][0]["message"]
    assert held.started == []


def test_a_huge_or_unbounded_grid_is_refused_before_it_is_expanded(tmp_path: Path) -> None:
    app, held = make_app(tmp_path, max_sweep_points=100)
    base = {"name": "s", "base": "baseline", "set": {"duration_s": 5, "detailed_loops": 0}}
    with serving(app) as c:
        t0 = time.monotonic()
        # 10^6 points answered 422 only after every combination was validated (minutes) before.
        spec = {**base, "grid": {"loops": {"start": 1, "stop": 1000, "step": 1},
                                 "duration_s": {"start": 1, "stop": 1000, "step": 1}}}
        r = c.post("/sweeps", json={"spec": spec}, headers=AUTH)
        assert r.status_code == 422 and "1000000 points" in r.json()["detail"][0]["message"], r.text
        # 10^9 values on one axis exhausted memory before anything was checked.
        spec = {**base, "grid": {"loops": {"start": 1, "stop": 1e9, "step": 1}}}
        r = c.post("/sweeps", json={"spec": spec}, headers=AUTH)
        assert r.status_code == 422 and "at most 1000" in r.json()["detail"][0]["message"], r.text
        for bad in ({"start": 1, "stop": 2, "step": 1e-308}, {"start": "NaN", "stop": 2, "step": 1}):
            r = c.post("/sweeps", json={"spec": {**base, "grid": {"loops": bad}}}, headers=AUTH)
            assert r.status_code == 422, (bad, r.status_code, r.text[:200])
        assert time.monotonic() - t0 < 10.0
    assert held.started == []


def raw_request(port: int, method: str, path: str, headers: dict[str, str], body: bytes = b"",
                chunks: list[bytes] | None = None) -> tuple[int, str]:
    """One request with exactly the head given (a declared length the body need not match, or a
    chunked body); the status and body of the answer."""
    conn = http.client.HTTPConnection("127.0.0.1", port, timeout=30)
    try:
        conn.putrequest(method, path, skip_accept_encoding=True)
        for k, v in headers.items():
            conn.putheader(k, v)
        conn.endheaders()
        try:
            if chunks is not None:
                for chunk in chunks:
                    conn.send(f"{len(chunk):x}\r\n".encode() + chunk + b"\r\n")
                conn.send(b"0\r\n\r\n")
            elif body:
                conn.send(body)
        except (BrokenPipeError, ConnectionResetError):
            pass  # answered (and closed) before the body was all sent
        resp = conn.getresponse()
        return resp.status, resp.read().decode(errors="replace")
    finally:
        conn.close()


def rss_mb() -> float:
    for line in Path("/proc/self/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1]) / 1024
    return 0.0


def test_a_large_body_is_refused_by_its_size_before_the_token_or_any_parsing(tmp_path: Path) -> None:
    """Four 16 MB bodies without a token moved the coordinator from 178 to 455 MB before each got
    its 401; a 100 000-deep JSON body without a token got 400, not 401."""
    app, held = make_app(tmp_path, max_body_bytes=1_000_000)
    with serving(app) as c:
        rss0 = rss_mb()
        big = {"content-type": "application/json", "content-length": str(16_000_000)}
        results: list[tuple[int, str]] = []
        threads = [threading.Thread(target=lambda: results.append(raw_request(c.port, "POST", "/runs", big)))
                   for _ in range(4)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
        assert [s for s, _ in results] == [413] * 4
        assert "max_body_bytes" in results[0][1] and "1000000 bytes" in results[0][1]
        # A chunked body declares no length: it is counted as it comes, with the token too.
        status, text = raw_request(c.port, "POST", "/runs", {**AUTH, "content-type": "application/json",
                                                             "transfer-encoding": "chunked"},
                                   chunks=[b" " * 400_000] * 3)
        assert status == 413, text
        deep = b"[" * 100_000 + b"]" * 100_000
        status, _ = raw_request(c.port, "POST", "/runs", {"content-type": "application/json",
                                                          "content-length": str(len(deep))}, deep)
        assert status == 401
        status, text = raw_request(c.port, "POST", "/runs", {**AUTH, "content-type": "application/json",
                                                             "content-length": str(len(deep))}, deep)
        assert status == 422 and "at most 32 levels" in text, (status, text[:200])
        # Brackets inside strings are no nesting; a scenario's few levels pass.
        body = json.dumps({"scenario": "smoke", "overrides": ["name=" + "[" * 100]}).encode()
        status, text = raw_request(c.port, "POST", "/runs", {**AUTH, "content-type": "application/json",
                                                             "content-length": str(len(body))}, body)
        assert status == 422 and "name" in text and "levels" not in text, (status, text[:200])
        assert rss_mb() - rss0 < 50
        metrics = c.get("/metrics", headers=AUTH).text
        assert 'cosim_coordinator_requests_refused_total{reason="body_size"} 5.0' in metrics
    assert held.started == []


def test_sweep_admission_is_exact_under_concurrency(tmp_path: Path) -> None:
    """12 concurrent POST /sweeps with max_queued 2 admitted 5 when sweeps were admitted outside
    the runs' lock."""
    app, _ = make_app(tmp_path, max_queued=2)
    with serving(app) as c:
        # NoPoints ends a sweep at once: hold them instead, so that they stay queued.
        jobs = app.app.state.jobs
        hold = threading.Event()
        jobs.make_executor = lambda slots: Held(hold)
        statuses: list[int] = []
        spec = {"spec": {"name": "s", "base": "baseline", "grid": {"loops": [2]},
                         "set": {"duration_s": 5, "detailed_loops": 0}}}

        def post() -> None:
            statuses.append(c.post("/sweeps", json=spec, headers=AUTH).status_code)

        threads = [threading.Thread(target=post) for _ in range(12)]
        for t in threads:
            t.start()
        for t in threads:
            t.join(60)
        assert sorted(statuses) == [201] * 2 + [429] * 10
        assert c.post("/runs", json={"scenario": "smoke"}, headers=AUTH).status_code == 429
        hold.set()


class Held:
    """A sweep executor that runs nothing until ``hold`` is set."""

    name = "held"

    def __init__(self, hold: threading.Event) -> None:
        self.hold = hold

    def run(self, tasks: list[PointTask], on_start: Any, on_done: Any, cancel: threading.Event) -> None:
        while not (self.hold.wait(0.1) or cancel.is_set()):
            pass


def test_a_request_names_no_file_of_the_coordinators_host(tmp_path: Path) -> None:
    """policy.learned_model from a request made the Edge open a system file."""
    app, held = make_app(tmp_path)
    with serving(app) as c:
        r = c.post("/runs", json={"scenario": "smoke", "overrides": ["policy.learned_model=/etc/passwd"]},
                   headers=AUTH)
        assert r.status_code == 422 and r.json()["detail"][0]["field"] == "policy.learned_model"
        base = {"name": "s", "base": "baseline", "grid": {"loops": [2]}, "set": {"duration_s": 5, "detailed_loops": 0}}
        for spec, field in (({**base, "set": {**base["set"], "policy.learned_model": "/etc/passwd"}},
                             "set.policy.learned_model"),
                            ({**base, "grid": {"loops": [2], "policy.learned_model": ["/etc/passwd"]}},
                             "grid.policy.learned_model[0]"),
                            # a whole section as an axis value
                            ({**base, "grid": {"loops": [2], "policy": [{"name": "learned",
                                                                         "learned_model": "/etc/passwd"}]}},
                             "grid.policy[0]"),
                            ({**base, "variants": {"v": {"policy.learned_model": "/etc/shadow"}}},
                             "variants.v.policy.learned_model")):
            r = c.post("/sweeps", json={"spec": spec}, headers=AUTH)
            assert r.status_code == 422, r.text
            assert field in [e["field"] for e in r.json()["detail"]], r.text
        # Infinite and NaN numbers are no limits.
        for value in ("inf", ".inf", "nan"):
            r = c.post("/runs", json={"scenario": "smoke", "overrides": [f"watchdog.window_timeout_s={value}"]},
                       headers=AUTH)
            assert r.status_code == 422 and r.json()["detail"][0]["field"] == "watchdog.window_timeout_s", r.text
    assert held.started == []


def test_answers_are_not_sniffed_nor_stored_and_the_docs_need_no_network(client: Client) -> None:
    for path in ("/healthz", "/runs", "/nope", "/"):
        r = client.get(path, headers=AUTH)
        assert r.headers["x-content-type-options"] == "nosniff" and r.headers["cache-control"] == "no-store"
    assert client.get("/runs").headers["x-content-type-options"] == "nosniff"  # the 401 too
    page = client.get("/docs", headers=AUTH).text
    scripts = re.findall(r"""(?:src|href)=["']([^"']+)""", page)
    assert scripts and all(s.startswith("/") for s in scripts), scripts
    for asset in ("/docs/swagger-ui-bundle.js", "/docs/swagger-ui.css"):
        r = client.get(asset, headers=AUTH)
        assert r.status_code == 200 and len(r.body) > 10_000
    assert client.get("/docs/../../etc/passwd", headers=AUTH).status_code == 404


def test_a_token_in_a_query_never_reaches_the_access_log(client: Client) -> None:
    import logging

    from interfaces.guard import RedactTokens

    access = logging.getLogger("uvicorn.access")
    assert any(isinstance(f, RedactTokens) for f in access.filters)
    record = logging.LogRecord("uvicorn.access", logging.INFO, __file__, 0, '%s - "%s %s HTTP/%s" %d',
                               ("127.0.0.1:5", "GET", f"/login?next=/&token={TOKEN}", "1.1", 303), None)
    for f in access.filters:
        f.filter(record)
    line = record.getMessage()
    assert TOKEN not in line and "token=***" in line and "next=/" in line


def test_a_body_of_escapes_is_read_in_one_pass() -> None:
    from interfaces.guard import _JSON_STRING, json_depth

    # An unterminated string of escapes is one match to its end, as a closed one is: without
    # that, the depth check tried again from every escape (1 MB of them took about an hour).
    unterminated = b'"' + b'\\"' * 500_000
    match = _JSON_STRING.match(unterminated)
    assert match is not None and match.end() == len(unterminated)
    assert json_depth(b'[' + unterminated[:2001]) == 1
    assert json_depth(b'{"a": [{"b": "[[["}]}') == 3


def test_login_with_more_query_fields_than_read_is_refused_not_an_error(client: Client) -> None:
    flood = "&".join(["a=1"] * 65)
    assert client.get(f"/login?{flood}").status_code == 401


def test_the_cookie_alone_changes_nothing_from_another_origin(tmp_path: Path) -> None:
    app, _ = make_app(tmp_path)
    with serving(app) as client:
        assert client.get("/login", params={"token": TOKEN}).status_code == 303
        assert client.get("/runs").status_code == 200, "the cookie reads from anywhere"
        before = origin_refusals(client)
        own = f"http://127.0.0.1:{client.port}"
        for origin in (None, f"http://127.0.0.1:{client.port + 1}", "http://elsewhere.example", "null"):
            headers = {} if origin is None else {"origin": origin}
            for path, body in (("/runs", {"scenario": "baseline", "overrides": {"duration_s": 0.2}}),
                               ("/runs/nosuchrun/cancel", None), ("/sweeps/nosuchsweep/cancel", None)):
                r = client.post(path, json=body, headers=headers)
                assert r.status_code == 403, (path, origin, r.status_code)
                assert "Origin" in r.json()["detail"] and "Bearer" in r.json()["detail"]
        # From the service's own pages (its Origin), or with the bearer header from anywhere, the
        # request goes on to its route (a 404: no such run).
        assert client.post("/runs/nosuchrun/cancel", headers={"origin": own}).status_code == 404
        assert client.post("/runs/nosuchrun/cancel", headers={"origin": "http://elsewhere.example",
                                                             **AUTH}).status_code == 404
        assert origin_refusals(client) - before == 12


def origin_refusals(client: Client) -> float:
    found = re.search(r'requests_refused_total\{reason="origin"\} ([0-9.]+)', client.get("/metrics", headers=AUTH).text)
    assert found is not None
    return float(found[1])
