"""Slots: how many simulations this host runs at once, shared by whatever starts them (the
coordinator's runs and its sweeps' points). A freed slot goes to the waiter of the highest
priority (the lowest number), first come first served among equals.
"""

from __future__ import annotations

import heapq
import itertools
import threading
from collections.abc import Iterator
from contextlib import contextmanager

# Who goes first when a slot frees: a run, then a sweep's point.
RUN_PRIORITY, POINT_PRIORITY = 0, 1


class Slots:
    """``size`` simulations at once on this host; waiters served by priority, then arrival."""

    def __init__(self, size: int) -> None:
        if size < 1:
            raise ValueError(f"slots must be >= 1, got {size}")
        self.size = size
        self._free = size
        self._cond = threading.Condition()
        self._waiting: list[tuple[int, int]] = []
        self._tickets = itertools.count()

    @contextmanager
    def take(self, priority: int, cancel: threading.Event | None = None) -> Iterator[bool]:
        """Hold a slot for the block: True, or False when ``cancel`` was set while waiting."""
        got = self._acquire(priority, cancel)
        try:
            yield got
        finally:
            if got:
                with self._cond:
                    self._free += 1
                    self._cond.notify_all()

    def _acquire(self, priority: int, cancel: threading.Event | None) -> bool:
        with self._cond:
            me = (priority, next(self._tickets))
            heapq.heappush(self._waiting, me)
            try:
                while not (self._free > 0 and self._waiting[0] == me):
                    if cancel is not None and cancel.is_set():
                        return False
                    self._cond.wait(0.2)  # a cancel sets no condition: look again now and then
                self._free -= 1
                return True
            finally:
                self._waiting.remove(me)
                heapq.heapify(self._waiting)
                self._cond.notify_all()

    def in_use(self) -> int:
        with self._cond:
            return self.size - self._free
