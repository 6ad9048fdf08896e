"""The transport every federate and the coordinator talk through.

``Bus`` is the interface; ``InMemoryHub``/``InMemoryBus`` implement it inside one process for
unit tests (with an optional hook to reorder deliveries), ``fabric.zenoh_bus`` over a
real zenoh router. Callbacks may run on a transport thread: handlers must only enqueue.
"""

from __future__ import annotations

import threading
from abc import ABC, abstractmethod
from collections.abc import Callable
from typing import Any

Callback = Callable[[str, bytes], None]
LivenessCallback = Callable[[str, bool], None]


def key_matches(pattern: str, key: str) -> bool:
    """Whether ``key`` matches the zenoh-style key expression ``pattern``: ``*`` is one segment,
    ``**`` any number of them (also zero)."""
    p, k = pattern.split("/"), key.split("/")

    def match(i: int, j: int) -> bool:
        if i == len(p):
            return j == len(k)
        if p[i] == "**":
            return any(match(i + 1, jj) for jj in range(j, len(k) + 1))
        if j == len(k):
            return False
        return (p[i] == "*" or p[i] == k[j]) and match(i + 1, j + 1)

    return match(0, 0)


class Bus(ABC):
    """Publish/subscribe transport with liveliness tokens."""

    @abstractmethod
    def publish(self, key: str, payload: bytes) -> None:
        """Send ``payload`` (bytes) under ``key`` to every subscription whose expression matches."""

    @abstractmethod
    def subscribe(self, key_expr: str, callback: Callback) -> Any:
        """Call ``callback(key, payload)`` for every publication matching ``key_expr``, possibly on
        a transport thread; returns the subscription's handle."""

    @abstractmethod
    def declare_token(self, key: str) -> Any:
        """Declare the liveliness token ``key``, withdrawn when the bus closes or the process
        dies; returns its handle."""

    @abstractmethod
    def watch_liveliness(self, key_expr: str, callback: LivenessCallback) -> Any:
        """Call ``callback(key, alive)`` for tokens matching ``key_expr`` appearing (also those
        that exist already) or vanishing."""

    @abstractmethod
    def close(self) -> None:
        """Drop this endpoint's subscriptions and withdraw its tokens; calling it again does
        nothing."""


class InMemoryHub:
    """Routes messages between ``InMemoryBus`` endpoints of one process.

    ``deliver`` can be replaced to delay or reorder deliveries (it receives the list of
    ``(callback, key, payload)`` triples of one publication and must eventually call each).
    """

    def __init__(self) -> None:
        self._lock = threading.RLock()
        self._subs: list[tuple[str, Callback]] = []
        self._tokens: set[str] = set()
        self._watchers: list[tuple[str, LivenessCallback]] = []
        self.deliver: Callable[[list[tuple[Callback, str, bytes]]], None] = self._deliver_now

    @staticmethod
    def _deliver_now(items: list[tuple[Callback, str, bytes]]) -> None:
        for cb, key, payload in items:
            cb(key, payload)

    def publish(self, key: str, payload: bytes) -> None:
        """Hand ``payload`` to ``deliver`` for every subscription matching ``key``."""
        with self._lock:
            items = [(cb, key, payload) for pat, cb in self._subs if key_matches(pat, key)]
        self.deliver(items)

    def subscribe(self, key_expr: str, callback: Callback) -> tuple[str, Callback]:
        """Add a subscription of ``callback(key, payload)`` to ``key_expr``; returns its entry,
        which ``unsubscribe`` takes."""
        entry = (key_expr, callback)
        with self._lock:
            self._subs.append(entry)
        return entry

    def unsubscribe(self, entry: tuple[str, Callback]) -> None:
        """Remove the subscription ``entry`` (from ``subscribe``), if still there."""
        with self._lock:
            if entry in self._subs:
                self._subs.remove(entry)

    def set_token(self, key: str, alive: bool) -> None:
        """Declare (``alive``) or withdraw the token ``key``, telling the watchers that match it."""
        with self._lock:
            if alive:
                self._tokens.add(key)
            else:
                self._tokens.discard(key)
            watchers = [cb for pat, cb in self._watchers if key_matches(pat, key)]
        for cb in watchers:
            cb(key, alive)

    def watch(self, key_expr: str, callback: LivenessCallback) -> None:
        """Call ``callback(key, alive)`` for tokens matching ``key_expr``: at once for those
        declared already, then on every change."""
        with self._lock:
            self._watchers.append((key_expr, callback))
            existing = [k for k in self._tokens if key_matches(key_expr, k)]
        for k in existing:
            callback(k, True)


class InMemoryBus(Bus):
    """One endpoint on an ``InMemoryHub``."""

    def __init__(self, hub: InMemoryHub) -> None:
        self.hub = hub
        self._subs: list[tuple[str, Callback]] = []
        self._tokens: list[str] = []
        self.closed = False

    def publish(self, key: str, payload: bytes) -> None:
        if not self.closed:
            self.hub.publish(key, payload)

    def subscribe(self, key_expr: str, callback: Callback) -> Any:
        entry = self.hub.subscribe(key_expr, callback)
        self._subs.append(entry)
        return entry

    def declare_token(self, key: str) -> Any:
        self._tokens.append(key)
        self.hub.set_token(key, True)
        return key

    def watch_liveliness(self, key_expr: str, callback: LivenessCallback) -> Any:
        self.hub.watch(key_expr, callback)

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        for entry in self._subs:
            self.hub.unsubscribe(entry)
        for key in self._tokens:
            self.hub.set_token(key, False)
