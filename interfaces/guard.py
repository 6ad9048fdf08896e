"""The API's front door: what every request passes before any route or parser sees it.

In order, each refusal costing no more than reading the request's head: body over the limit
(413), token (401), a change asked with the cookie alone from another origin (403), body read up
to the limit (413) and nested deeper than ``MAX_JSON_DEPTH`` (422); docs/docker.md, "Who may use
the API".
"""

from __future__ import annotations

import json
import logging
import re
from collections.abc import Awaitable, Callable, MutableMapping
from typing import Any
from urllib.parse import parse_qs

from interfaces.auth import token_matches

Scope = MutableMapping[str, Any]
Message = MutableMapping[str, Any]
Receive = Callable[[], Awaitable[Message]]
Send = Callable[[Message], Awaitable[None]]
App = Callable[[Scope, Receive, Send], Awaitable[None]]

COOKIE = "cosim5g_token"
# Methods that read: the cookie alone may ask them from anywhere a browser sends it.
SAFE_METHODS = frozenset({"GET", "HEAD", "OPTIONS"})
# Routes anyone may call: liveness only (the compose healthcheck and load balancers know no token).
PUBLIC_PATHS = frozenset({"/healthz"})
# A token in a query (``/login?token=...``): shown as *** in the access log.
_QUERY_TOKEN = re.compile(r"(?<=[?&]token=)[^&\s]*")
# The deepest JSON a request may nest (a scenario or a sweep spec needs under 10 levels); deeper
# is refused before any parser recurses into it.
MAX_JSON_DEPTH = 32
# A string to its closing quote, or to the end of an unterminated one: matched in one pass
# (a required closing quote made an unterminated string of escapes cost the square of its length).
_JSON_STRING = re.compile(rb'"(?:[^"\\]|\\.)*"?')
_NOT_BRACKETS = bytes(b for b in range(256) if b not in b"[]{}")


class Guard:
    """ASGI middleware around the whole app. ``refused``: the 401's detail (where the token is);
    ``on_refused(reason)``: counts a refusal ("token" or "body_size")."""

    def __init__(self, app: App, *, token: str, max_body_bytes: int, refused: str,
                 on_refused: Callable[[str], None] = lambda reason: None) -> None:
        self.app, self.token, self.max_body_bytes = app, token, max_body_bytes
        self.refused, self.on_refused = refused, on_refused

    async def __call__(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope["type"] != "http":
            await self.app(scope, receive, send)
            return
        send = _safe_headers(send)
        headers = _headers(scope)
        declared = headers.get("content-length")
        if declared is not None and (not (declared.isascii() and declared.isdigit())
                                     or int(declared) > self.max_body_bytes):
            await self._too_large(send)
            return
        if scope["path"] not in PUBLIC_PATHS:
            credential = self._credential(scope, headers)
            if credential is None:
                self.on_refused("token")
                await _answer(send, 401, self.refused, [(b"www-authenticate", b"Bearer")])
                return
            if credential == "cookie" and scope["method"] not in SAFE_METHODS and not _same_origin(headers):
                # SameSite=Strict does not tell this service from another port of the same host,
                # whose page could otherwise start or cancel work with the user's cookie.
                self.on_refused("origin")
                await _answer(send, 403, f"a {scope['method']} authorised by the login cookie alone must come "
                                         "from this service's own pages (its Origin header, "
                                         f"{headers.get('origin', 'absent')!r}, is not {headers.get('host', '')!r}): "
                                         "send the token as an 'Authorization: Bearer' header")
                return
        body = await self._body(receive)
        if body is None:
            await self._too_large(send)
            return
        if json_depth(body) > MAX_JSON_DEPTH:
            self.on_refused("json_depth")
            await _answer(send, 422, f"the request body nests deeper than this coordinator reads: "
                                     f"at most {MAX_JSON_DEPTH} levels of arrays and objects")
            return
        await self.app(scope, _replay(body, receive), send)

    def _credential(self, scope: Scope, headers: dict[str, str]) -> str | None:
        """Which of the bearer header, the cookie or (on /login only, which checks it again
        itself) the query's token is the token, the first that is; None if none is. A stale
        cookie does not stand in the way of a login."""
        given = []
        scheme, _, credentials = headers.get("authorization", "").partition(" ")
        if scheme.lower() == "bearer" and credentials:
            given.append(("bearer", credentials.strip()))
        if (cookie := _cookie(headers.get("cookie", ""), COOKIE)) is not None:
            given.append(("cookie", cookie))
        if scope["path"] == "/login" and (query := _query_value(
                scope.get("query_string", b"").decode("latin-1"), "token")) is not None:
            given.append(("query", query))
        return next((kind for kind, g in given if token_matches(g, self.token)), None)

    async def _body(self, receive: Receive) -> bytes | None:
        """The whole body, or None once it passes the limit (a chunked body declares no length)."""
        chunks, size = [], 0
        while True:
            message = await receive()
            if message["type"] != "http.request":
                break
            chunk = message.get("body", b"")
            size += len(chunk)
            if size > self.max_body_bytes:
                return None
            chunks.append(chunk)
            if not message.get("more_body", False):
                break
        return b"".join(chunks)

    async def _too_large(self, send: Send) -> None:
        self.on_refused("body_size")
        await _answer(send, 413, f"the request body is larger than this coordinator accepts: max_body_bytes "
                                 f"(--max-body-bytes, COSIM5G_MAX_BODY_BYTES) = {self.max_body_bytes} bytes")


def json_depth(body: bytes) -> int:
    """How deep ``body``'s arrays and objects nest, counted without parsing it (strings, where a
    bracket means nothing, are left out first)."""
    brackets = _JSON_STRING.sub(b"", body).translate(None, _NOT_BRACKETS)
    depth = deepest = 0
    for c in brackets:
        depth += 1 if c in b"[{" else -1
        deepest = max(deepest, depth)
    return deepest


def _headers(scope: Scope) -> dict[str, str]:
    return {k.decode("latin-1").lower(): v.decode("latin-1") for k, v in scope.get("headers", [])}


def _same_origin(headers: dict[str, str]) -> bool:
    """Whether the request's ``Origin`` (which a browser sends with every POST) is this service,
    as the client addressed it (``Host``). No Origin is not a browser's request: refused too."""
    origin, host = headers.get("origin"), headers.get("host")
    return bool(origin and host) and origin in (f"http://{host}", f"https://{host}")


def _cookie(header: str, name: str) -> str | None:
    for part in header.split(";"):
        key, sep, value = part.strip().partition("=")
        if sep and key == name:
            return value
    return None


def _query_value(query: str, name: str) -> str | None:
    try:
        values = parse_qs(query, max_num_fields=64).get(name)
    except ValueError:  # more fields than that: no token read from it
        return None
    return values[0] if values else None


def _replay(body: bytes, receive: Receive) -> Receive:
    """A receive that hands the app the body already read, then waits on the client as before."""
    sent = False

    async def replay() -> Message:
        nonlocal sent
        if not sent:
            sent = True
            return {"type": "http.request", "body": body, "more_body": False}
        return await receive()

    return replay


def _safe_headers(send: Send) -> Send:
    """Every answer is not sniffed, and not stored by a browser or proxy (pages and results are
    the token holder's; a shared machine's cache would keep them past the session)."""
    async def wrapped(message: Message) -> None:
        if message["type"] == "http.response.start":
            headers = list(message.get("headers", []))
            if not any(k.lower() == b"cache-control" for k, _ in headers):
                headers.append((b"cache-control", b"no-store"))
            message["headers"] = [*headers, (b"x-content-type-options", b"nosniff")]
        await send(message)

    return wrapped


async def _answer(send: Send, status: int, detail: str, extra: list[tuple[bytes, bytes]] | None = None) -> None:
    body = json.dumps({"detail": detail}).encode()
    await send({"type": "http.response.start", "status": status,
                "headers": [(b"content-type", b"application/json"), (b"content-length", str(len(body)).encode()),
                            *(extra or [])]})
    await send({"type": "http.response.body", "body": body})


class RedactTokens(logging.Filter):
    """Shows a token in an access-log line's query as ``***``."""

    def filter(self, record: logging.LogRecord) -> bool:
        if isinstance(record.args, tuple) and any(isinstance(a, str) and "token=" in a for a in record.args):
            record.args = tuple(_QUERY_TOKEN.sub("***", a) if isinstance(a, str) else a for a in record.args)
        return True


def redact_access_log() -> None:
    """Install ``RedactTokens`` on uvicorn's access log (once)."""
    access = logging.getLogger("uvicorn.access")
    if not any(isinstance(f, RedactTokens) for f in access.filters):
        access.addFilter(RedactTokens())
