"""How a node's jobs of one kind wait for it: all in arrival order, or only each source's newest.

An Edge estimating the frames of many loops on one node can fall behind them. In arrival order
(``fifo``) every frame is estimated, however old it is by then; with ``newest`` a frame waiting
for the node is replaced by its loop's next one, as a vision pipeline keeps only the latest
image of each camera. The detail: docs/compute.md, "Which frames a busy Edge estimates".
"""

from __future__ import annotations

from collections.abc import Callable, Hashable
from typing import Any, Literal

from fabric.compute import ComputeNode

QueueMode = Literal["fifo", "newest"]
QUEUE_MODES: tuple[QueueMode, ...] = ("fifo", "newest")

# A federate's ``schedule``: run ``fn(*args)`` at simulated time ``t_us``.
Schedule = Callable[..., Any]


class JobQueue:
    """The jobs of ``kind`` that sources (``key``: a loop) hand to ``node``.

    ``fifo``: each job is queued on the node as it arrives (``ComputeNode.run`` fixes its start
    and end at once). ``newest``: a job arriving while a core is free starts at once; otherwise it
    waits outside the node, one per key, a newer one of the same key taking the older's place in
    line (the older is dropped: ``dropped(*done_args)``); the waiting keys are served in the order
    they began to wait as cores free up. Either way ``done(*done_args, result, ready_us)`` is
    called as the job is run, ``ready_us`` the simulated time at which it ends."""

    def __init__(self, node: ComputeNode, kind: str, mode: QueueMode, schedule: Schedule,
                 dropped: Callable[..., None] | None = None) -> None:
        if mode not in QUEUE_MODES:
            raise ValueError(f"queue mode {mode!r}: one of {', '.join(QUEUE_MODES)}")
        self.node = node
        self.kind = kind
        self.mode = mode
        self._schedule = schedule
        self._dropped = dropped
        # key -> (arrival us, fn, args, done, done_args), in arrival order.
        self._waiting: dict[Hashable, tuple[int, Callable[..., Any], tuple[Any, ...], Callable[..., None],
                                            tuple[Any, ...]]] = {}
        self._serve_at: int | None = None  # when a service event is due

    @property
    def waiting(self) -> int:
        """Jobs waiting outside the node (``newest`` only)."""
        return len(self._waiting)

    def waiting_jobs(self) -> list[tuple[Any, ...]]:
        """The ``done_args`` of the jobs waiting (``newest``), in line: at a run's end, the
        frames complete and not estimated yet."""
        return [job[4] for job in self._waiting.values()]

    def submit(self, now_us: int, key: Hashable, fn: Callable[..., Any], args: tuple[Any, ...],
               done: Callable[..., None], done_args: tuple[Any, ...]) -> None:
        """A job ``fn(*args)`` of source ``key`` arrives at ``now_us``."""
        if self.mode == "fifo":
            result, ready = self.node.run(self.kind, now_us, fn, *args)
            done(*done_args, result, ready)
            return
        old = self._waiting.get(key)
        if old is not None and self._dropped is not None:
            self._dropped(*old[4])
        # A newer job takes the older's place in line, so that a source whose jobs keep replacing
        # each other is still served in its turn.
        self._waiting[key] = (now_us, fn, args, done, done_args)
        self._serve(now_us)

    def _serve(self, now_us: int) -> None:
        if self._serve_at == now_us:
            self._serve_at = None
        while self._waiting and self.node.free_us <= now_us:
            key = next(iter(self._waiting))
            arrival, fn, args, done, done_args = self._waiting.pop(key)
            # The node's free core starts it now: the wait shows as the job's queueing delay.
            result, ready = self.node.run(self.kind, arrival, fn, *args)
            done(*done_args, result, ready)
        if self._waiting:
            # Another kind's job may take the node first; the service then looks again.
            at = max(now_us, self.node.free_us)
            if self._serve_at is None or at < self._serve_at:
                self._serve_at = at
                self._schedule(at, self._serve, at)
