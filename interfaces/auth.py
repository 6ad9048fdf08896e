"""Who may use the coordinator's REST API: the bearer token, its file, and where the API listens.

``COSIM5G_TOKEN``, else the token file the coordinator writes at its first start (default
``results/auth/api-token``), found the same way by clients: docs/docker.md, "Who may use the API".
"""

from __future__ import annotations

import hmac
import os
import secrets
import socket
import stat
import time
from pathlib import Path

from fabric.settings import env_name, settings

TOKEN_ENV = env_name("token")
TOKEN_FILE_ENV = env_name("token_file")
DEFAULT_TOKEN_FILE = Path("results") / "auth" / "api-token"
# Shorter tokens are refused: a guessable token is no protection.
MIN_TOKEN_CHARS = 16


class TokenError(RuntimeError):
    """The token cannot be read, written or used; the message says how to fix it."""


def token_file(explicit: str | Path | None = None) -> Path:
    """The token file: ``explicit`` if given, else ``COSIM5G_TOKEN_FILE``, else the default."""
    if explicit:
        return Path(explicit)
    return settings().token_file or DEFAULT_TOKEN_FILE


def _checked(token: str, source: str) -> str:
    token = token.strip()
    if len(token) < MIN_TOKEN_CHARS or any(c.isspace() for c in token) or not token.isprintable():
        raise TokenError(f"the API token from {source} must be at least {MIN_TOKEN_CHARS} printable "
                         "characters without spaces")
    return token


def _read_private(path: Path) -> str:
    try:
        st = path.stat()
        if st.st_mode & (stat.S_IRWXG | stat.S_IRWXO):
            raise TokenError(f"token file {path} is readable by others (mode {stat.S_IMODE(st.st_mode):04o}): "
                             f"chmod 600 {path}, or remove it to have a new token generated")
        text = path.read_text()
    except OSError as exc:
        raise TokenError(f"cannot read the token file {path}: {exc.strerror}; run as its owner, or give "
                         f"another with --token-file / {TOKEN_FILE_ENV}, or set {TOKEN_ENV}") from None
    return _checked(text, str(path))


def server_token(path: Path, keep_env_token: bool = False) -> str:
    """The token a coordinator accepts: ``COSIM5G_TOKEN``, else the file at ``path``, which is
    created (random, mode 0600, its folder 0700) if it does not exist yet. ``keep_env_token``:
    a ``COSIM5G_TOKEN`` is also written to ``path`` (replacing what it held)."""
    env = settings().token
    if env:
        token = _checked(env, TOKEN_ENV)
        if keep_env_token:
            _write_private(path, token, replace=True)
        return token
    if path.exists():
        return _read_private(path)
    token = secrets.token_urlsafe(32)
    # Exclusive: of two coordinators starting at once, one writes and the other reads its token.
    if not _write_private(path, token, replace=False):
        return _read_private(path)
    return token


def _write_private(path: Path, token: str, replace: bool) -> bool:
    """Write ``token`` to ``path`` (mode 0600, folder 0700); False if ``path`` exists and not
    ``replace``. Replacing goes through a new file and a rename: no reader sees half a token."""
    target = path.with_name(f".{path.name}.new") if replace else path
    try:
        path.parent.mkdir(mode=0o700, parents=True, exist_ok=True)
        if replace:
            target.unlink(missing_ok=True)
        fd = os.open(target, os.O_WRONLY | os.O_CREAT | os.O_EXCL, 0o600)
    except FileExistsError:
        return False
    except OSError as exc:
        raise TokenError(f"cannot write the token file {path}: {exc.strerror}; make its folder writable, "
                         f"or give another with --token-file / {TOKEN_FILE_ENV}") from None
    with os.fdopen(fd, "w") as f:
        f.write(token + "\n")
    if replace:
        os.replace(target, path)
    return True


def client_token(path: str | Path | None = None) -> str | None:
    """The token a client sends: ``COSIM5G_TOKEN``, else the token file's content, else None."""
    env = settings().token
    if env:
        return env.strip()
    p = token_file(path)
    try:
        return p.read_text().strip() or None
    except OSError:
        return None


def token_matches(given: str, expected: str) -> bool:
    """Constant-time comparison: the time taken says nothing about how much of a guess was right."""
    return hmac.compare_digest(given.encode(), expected.encode())


def listen_sockets(hosts: list[str], port: int, resolve_timeout_s: float = 10.0) -> list[socket.socket]:
    """Bound TCP sockets, one per address of each host (names are resolved, at start only).

    Binding addresses rather than 0.0.0.0 is what keeps the API off networks the process joins
    later: the compose coordinator is connected to every run network (federates reach its zenoh
    router there), and listens only on loopback and its platform-network address."""
    socks: list[socket.socket] = []
    seen: set[tuple[str, int]] = set()  # (address, family)
    try:
        for host in hosts:
            deadline = time.monotonic() + resolve_timeout_s
            while True:
                try:
                    infos = socket.getaddrinfo(host, port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)
                    break
                except socket.gaierror as exc:  # a container's DNS may lag its start by a moment
                    if time.monotonic() > deadline:
                        raise OSError(f"cannot resolve --host {host!r}: {exc.strerror}") from None
                    time.sleep(0.5)
            for family, kind, proto, _, addr in infos:
                key = (str(addr[0]), int(family))
                if key in seen:
                    continue
                seen.add(key)
                s = socket.socket(family, kind, proto)
                s.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
                if family == socket.AF_INET6:
                    s.setsockopt(socket.IPPROTO_IPV6, socket.IPV6_V6ONLY, 1)
                try:
                    s.bind(addr)
                except OSError as exc:
                    s.close()
                    raise OSError(f"cannot listen on {addr[0]} port {port}: {exc.strerror}") from None
                socks.append(s)
    except OSError:
        for s in socks:
            s.close()
        raise
    return socks
