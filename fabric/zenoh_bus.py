"""The Bus over eclipse-zenoh: a client session for federates, a router session for the coordinator.

Scouting off and explicit endpoints, so runs on one host never find each other; every publication
blocks under congestion, so a frame is never silently dropped (docs/architecture.md sec. 4). The
lease after which a vanished peer counts as dead: ``session_config``.
"""

from __future__ import annotations

import json
import time
from typing import Any

import zenoh

from fabric.bus import Bus, Callback, LivenessCallback

LEASE_MS = 5000
KEEP_ALIVES_PER_LEASE = 4
CLOSE_DRAIN_S = 0.05  # see close()


def session_config(mode: str, endpoint: str) -> zenoh.Config:
    """A zenoh config: ``mode`` 'router' listens on ``endpoint`` (e.g. ``tcp/127.0.0.1:7447``),
    'client' or 'peer' connects to it; no multicast scouting, no shared memory, a lease of
    ``LEASE_MS``. A peer that vanishes without closing its connection (a host or container gone,
    a network cut) is declared dead after that lease, which withdraws its liveliness tokens: a
    shorter lease than zenoh's default 10 s lets a federate notice a lost coordinator, and leave,
    within 10 s."""
    if mode not in ("router", "client", "peer"):
        raise ValueError(f"zenoh mode {mode!r} is not one of router, client, peer")
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(mode))
    conf.insert_json5("scouting/multicast/enabled", "false")
    # With no multicast scouting there is nothing to wait for: the default delay (500 ms) made
    # opening the router half a second of every run.
    conf.insert_json5("scouting/delay", "0")
    # Zenoh would put every message over 3 kB into a 16 MiB shared-memory pool per session, and a
    # router keeps the pools of every client it ever met mapped: a long-lived coordinator grew by
    # two segments (~20 MiB, 2 descriptors) per run. Loopback TCP carries the frames instead.
    conf.insert_json5("transport/shared_memory/enabled", "false")
    conf.insert_json5("transport/link/tx/lease", str(LEASE_MS))
    conf.insert_json5("transport/link/tx/keep_alive", str(KEEP_ALIVES_PER_LEASE))
    if mode == "router":
        conf.insert_json5("listen/endpoints", json.dumps([endpoint]))
    else:
        conf.insert_json5("connect/endpoints", json.dumps([endpoint]))
    return conf


class ZenohBus(Bus):
    """A Bus backed by one zenoh session, opened at once: ``mode`` 'client' (a federate)
    connects to the router at ``endpoint``, 'router' (the coordinator) listens there."""

    def __init__(self, endpoint: str, mode: str = "client") -> None:
        self.endpoint = endpoint
        self.session = zenoh.open(session_config(mode, endpoint))
        self._publishers: dict[str, Any] = {}
        self._keep: list[Any] = []
        self._closed = False

    def publish(self, key: str, payload: bytes) -> None:
        pub = self._publishers.get(key)
        if pub is None:
            pub = self.session.declare_publisher(
                key, congestion_control=zenoh.CongestionControl.BLOCK
            )
            self._publishers[key] = pub
        pub.put(payload)

    def subscribe(self, key_expr: str, callback: Callback) -> Any:
        def handler(sample: zenoh.Sample) -> None:
            callback(str(sample.key_expr), sample.payload.to_bytes())

        sub = self.session.declare_subscriber(key_expr, handler)
        self._keep.append(sub)
        return sub

    def declare_token(self, key: str) -> Any:
        token = self.session.liveliness().declare_token(key)
        self._keep.append(token)
        return token

    def watch_liveliness(self, key_expr: str, callback: LivenessCallback) -> Any:
        def handler(sample: zenoh.Sample) -> None:
            callback(str(sample.key_expr), sample.kind == zenoh.SampleKind.PUT)

        sub = self.session.liveliness().declare_subscriber(key_expr, history=True, handler=handler)
        self._keep.append(sub)
        return sub

    def close(self) -> None:
        if self._closed:
            return
        self._closed = True
        # zenoh batches puts for up to about a millisecond, and closing the session drops what
        # is not yet written: a process's last messages (its final report) must leave first.
        time.sleep(CLOSE_DRAIN_S)
        for pub in self._publishers.values():
            pub.undeclare()
        self._publishers.clear()
        self._keep.clear()
        self.session.close()
