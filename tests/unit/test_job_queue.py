"""How an Edge's pose jobs wait for its node: every frame in arrival order, or each loop's newest."""

from __future__ import annotations

import heapq
from collections.abc import Callable
from typing import Any

import numpy as np
import pytest

from fabric.compute import ComputeNode
from fabric.job_queue import JobQueue
from scenario.schema import JobModel, NodeProfile


class Clock:
    """The federate's event heap, as much of it as the queue uses."""

    def __init__(self) -> None:
        self.now = 0
        self._heap: list[tuple[int, int, Callable[..., None], tuple[Any, ...]]] = []
        self._seq = 0

    def schedule(self, t_us: int, fn: Callable[..., None], *args: Any) -> None:
        assert t_us >= self.now
        self._seq += 1
        heapq.heappush(self._heap, (t_us, self._seq, fn, args))

    def run(self) -> None:
        while self._heap:
            self.now, _, fn, args = heapq.heappop(self._heap)
            fn(*args)


def node(cpus: float = 1.0, pose_us: int = 10_000) -> ComputeNode:
    profile = NodeProfile(cpus=cpus, timing="model", model_us={"pose": JobModel(mean_us=pose_us),
                                                                "policy": JobModel(mean_us=1_000)})
    return ComputeNode("edge", profile, np.random.default_rng(0))


def drive(mode: str, arrivals: list[tuple[int, int]], cpus: float = 1.0,
          policy_at: list[int] = ()) -> tuple[list[tuple[int, int, int, int]], list[int], JobQueue]:
    """Frames ``(t_us, loop)`` handed to a queue of ``mode``: the estimates as (loop, frame,
    start us, ready us), in the order they were run, the frames dropped, and the queue."""
    clock = Clock()
    done: list[tuple[int, int, int, int]] = []
    dropped: list[int] = []
    cpu = node(cpus)
    q = JobQueue(cpu, "pose", mode, clock.schedule, lambda loop, frame: dropped.append(frame))  # type: ignore[arg-type]

    def estimated(loop: int, frame: int, result: int, ready: int) -> None:
        assert result == frame * 2  # the job's own work ran
        done.append((loop, frame, cpu.records[-1].start_us, ready))

    for frame, (t, loop) in enumerate(arrivals):
        clock.schedule(t, lambda t=t, loop=loop, frame=frame: q.submit(
            t, loop, lambda f: f * 2, (frame,), estimated, (loop, frame)))
    for t in policy_at:
        clock.schedule(t, lambda t=t: cpu.run("policy", t, int, 0))
    clock.run()
    return done, dropped, q


# Two loops sending a frame each every 10 ms to a node that estimates one in 10 ms: it can keep up
# with one of them.
BURST = [(t, loop) for t in range(0, 100_000, 10_000) for loop in (0, 1)]


def test_fifo_estimates_every_frame_however_long_it_waits() -> None:
    done, dropped, q = drive("fifo", BURST)
    assert [f for _, f, _, _ in done] == list(range(20)) and not dropped
    # The backlog grows by a frame every 10 ms: the last frame waits 100 ms.
    assert done[-1][2] - BURST[-1][0] == 100_000
    assert q.waiting == 0


def test_newest_keeps_one_frame_per_loop_waiting_and_drops_the_older() -> None:
    done, dropped, _ = drive("newest", BURST)
    assert len(done) + len(dropped) == 20
    # No frame waits longer than the one in service and the other loop's ahead of it.
    waits = [start - BURST[f][0] for _, f, start, _ in done]
    assert max(waits) <= 20_000, waits
    # Both loops are served (the oldest waiting first), and what is dropped is an older frame of
    # a loop whose newer one was estimated.
    assert {loop for loop, _, _, _ in done} == {0, 1}
    for f in dropped:
        loop = BURST[f][1]
        assert any(lp == loop and g > f for lp, g, _, _ in done)
    # The node never idles while a frame waits: one estimate every 10 ms from the first.
    starts = [start for _, _, start, _ in done]
    assert starts == list(range(0, 10_000 * len(done), 10_000))


def test_newest_starts_a_frame_at_once_on_an_idle_node() -> None:
    done, dropped, _ = drive("newest", [(0, 0), (50_000, 0), (100_000, 1)])
    assert [(loop, start, ready) for loop, _, start, ready in done] == \
        [(0, 0, 10_000), (0, 50_000, 60_000), (1, 100_000, 110_000)] and not dropped


def test_newest_uses_every_core_of_a_node() -> None:
    # Two cores: the two loops' frames, 10 ms apart each, fit.
    done, dropped, _ = drive("newest", BURST, cpus=2.0)
    assert len(done) == 20 and not dropped
    assert all(start == BURST[f][0] for _, f, start, _ in done)


def test_newest_waits_for_a_job_of_another_kind_that_took_the_node() -> None:
    # A policy job (1 ms) queued on the node at 10 ms, as its frame-0 estimate ends: the waiting
    # frame starts after it, never before its end.
    done, _, _ = drive("newest", [(0, 0), (5_000, 1)], policy_at=[10_000])
    assert [(loop, start) for loop, _, start, _ in done] == [(0, 0), (1, 11_000)]


def test_fifo_and_newest_run_the_same_jobs_when_the_node_keeps_up() -> None:
    light = [(t, loop) for t in range(0, 200_000, 40_000) for loop in (0, 1)]
    assert drive("fifo", light)[0] == drive("newest", light)[0]


def test_an_unknown_mode_is_refused_naming_the_allowed() -> None:
    with pytest.raises(ValueError, match="fifo, newest"):
        JobQueue(node(), "pose", "lifo", lambda *a: None)  # type: ignore[arg-type]


def test_the_jobs_still_waiting_are_listed_in_line() -> None:
    clock = Clock()
    dropped: list[tuple[int, int]] = []
    q = JobQueue(node(), "pose", "newest", clock.schedule, lambda *job: dropped.append(job))
    for loop, frame in ((0, 0), (1, 1), (2, 2), (1, 3)):
        q.submit(0, loop, int, (), lambda *a: None, (loop, frame))
    # Loop 0's frame runs; loop 1's newer frame waits in its older one's place, before loop 2's.
    assert q.waiting_jobs() == [(1, 3), (2, 2)] and q.waiting == 2 and dropped == [(1, 1)]
