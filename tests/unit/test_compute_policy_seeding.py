"""Compute emulation timing modes, co-design policies and named random streams."""

from __future__ import annotations

import numpy as np
import pytest

from domain.loop_state import LoopState
from domain.policy import make_policy
from fabric.compute import ComputeNode
from fabric.host_speed import HostScore, reference
from fabric.seeding import rng
from scenario.schema import JobModel, NodeProfile, PolicyConfig


def busy(n: int) -> int:
    return sum(i * i for i in range(n))


def test_model_timing_is_seeded_and_queues_jobs() -> None:
    prof = NodeProfile(cpus=0.5, timing="model", model_us={"job": JobModel(mean_us=10_000, sd_us=1000)})
    a = ComputeNode("n", prof, rng(1, "n"))
    b = ComputeNode("n", prof, rng(1, "n"))
    ends_a = [a.run("job", 0, busy, 1000)[1] for _ in range(3)]
    ends_b = [b.run("job", 0, busy, 1000)[1] for _ in range(3)]
    assert ends_a == ends_b
    assert ends_a[0] < ends_a[1] < ends_a[2]  # one core: jobs that arrive together queue
    assert a.records[2].queue_us == ends_a[1]


def test_cpu_timing_scales_with_node_speed() -> None:
    # A host as fast as the reference core (injected): the duration is the job's CPU time / cpus.
    ref = reference()
    slow = ComputeNode("s", NodeProfile(cpus=0.25, timing="cpu"), rng(1, "s"),
                       host=HostScore(score=ref.score, source="injected"), probe=lambda: ref.score)
    _, end = slow.run("job", 0, busy, 200_000)
    rec = slow.records[0]
    assert end == rec.duration_us
    assert rec.duration_us == pytest.approx(rec.cpu_us / 0.25, abs=5)  # one thread: 1 / cpus


def test_policies_share_one_interface() -> None:
    track_far = {"id": 0, "t_us": 0, "p": [-0.55, 0, 0.78], "v": [0.2, 0, 0], "sd": 0.003}
    track_near = {"id": 1, "t_us": 0, "p": [-0.3, 0, 0.78], "v": [0.2, 0, 0], "sd": 0.003}
    cfg = PolicyConfig(name="heuristic", idle_pdp=0.2, track_pdp=0.5, approach_s=0.5, pdp=0.7)

    def state(tracks: list, now: int = 0) -> LoopState:
        return LoopState(now, tracks, 0, 0.2)

    h = make_policy(cfg)
    assert h.decide(state([])).pdp == 0.2
    assert h.decide(state([track_far])).pdp == 0.5
    assert h.decide(state([track_near])).pdp == 1.0
    assert h.decide(state([track_far], now=400_000)).pdp == 1.0  # stale estimate
    assert make_policy(cfg.model_copy(update={"name": "none"})).decide(state([])).pdp == 1.0
    assert make_policy(cfg.model_copy(update={"name": "fixed"})).decide(state([])).pdp == 0.7


def test_named_streams_are_independent_of_order() -> None:
    a1 = rng(5, "camera-0/pdp").random(3)
    rng(5, "camera-1/pdp").random(3)
    a2 = rng(5, "camera-0/pdp").random(3)
    assert np.array_equal(a1, a2)
    assert not np.array_equal(a1, rng(6, "camera-0/pdp").random(3))
