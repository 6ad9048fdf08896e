"""A thread that steps the world ahead while the group's thread processes the other members' events.

``mj_step`` releases the GIL, so a step in this thread runs on the second core. The work is handed
over once a simulated millisecond at 32 loops, so the handover is three locks used as binary
semaphores: ``acquire`` waits in C with the GIL released and a ``release`` from the other thread
wakes it, with less Python around each handover than an executor's futures and events.
"""

from __future__ import annotations

import threading
from collections.abc import Callable


class StepAhead:
    """Runs ``advance(t_us)`` in a thread of its own, one call at a time."""

    def __init__(self, advance: Callable[[int], None], name: str) -> None:
        self._advance = advance
        self._go, self._started, self._done = threading.Lock(), threading.Lock(), threading.Lock()
        for lock in (self._go, self._started, self._done):
            lock.acquire()  # each is released by one side and taken by the other
        self._target = 0
        self._error: BaseException | None = None
        self._closing = False
        self.running = False
        self._thread = threading.Thread(target=self._loop, name=name, daemon=True)
        self._thread.start()

    def start(self, t_us: int) -> None:
        """Begin ``advance(t_us)``; returns once it holds the GIL, so that it starts now rather than
        when the caller next lets go of the GIL (it lets go inside ``mj_step``)."""
        if self.running:
            raise RuntimeError("a step ahead is running already")
        self._target = t_us
        self.running = True
        self._go.release()
        self._started.acquire()

    def wait(self) -> None:
        """Wait for the running call, if any; its exception is raised here."""
        if not self.running:
            return
        self._done.acquire()
        self.running = False
        error, self._error = self._error, None
        if error is not None:
            raise error

    def close(self) -> None:
        """Wait for the running call (its error is not raised again) and end the thread."""
        if self.running:
            self._done.acquire()
            self.running = False
        self._closing = True
        self._go.release()
        self._thread.join(timeout=10)

    def _loop(self) -> None:
        while True:
            self._go.acquire()
            if self._closing:
                return
            self._started.release()
            try:
                self._advance(self._target)
            except BaseException as exc:  # handed to the caller's thread by ``wait``
                self._error = exc
            self._done.release()
