"""The states of a run, of a sweep and of each of its points: one set of words for all three."""

from __future__ import annotations

from enum import StrEnum


class RunState(StrEnum):
    """Where a run is (a sweep and each of its points too); the last four are ends, and a run
    ends in exactly one of them."""

    PENDING = "pending"
    RUNNING = "running"
    COMPLETED = "completed"
    FAILED = "failed"
    TIMED_OUT = "timed_out"
    CANCELLED = "cancelled"


ACTIVE = (RunState.PENDING, RunState.RUNNING)
ENDED = (RunState.COMPLETED, RunState.FAILED, RunState.TIMED_OUT, RunState.CANCELLED)
