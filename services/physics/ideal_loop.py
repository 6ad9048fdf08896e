"""Pick-and-place loops closed without a network, to test and benchmark the physics and controller.

Each cell's real ``PickController`` gets each camera frame's ground-truth part poses after a fixed
delay, frames lost independently, or by the abstract loops' path (Gaussian error, the Edge's
Kalman tracker). Spawns, camera phases, local wires and control periods are the federation's
(same named streams); no netsim, no rendering, no estimator.
"""

from __future__ import annotations

import heapq
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from domain import work_cell as g
from domain.arm import SERVO_LAG_S
from domain.controller import PickController
from domain.sensor import frame_offset_us
from domain.tracker import Tracker
from domain.world import World, spawn_plan
from fabric.seeding import rng
from scenario.schema import Scenario


@dataclass
class IdealLoopResult:
    tasks: list[dict[str, Any]]  # finished tasks (outcome != unfinished)
    frames: int = 0
    frames_delivered: int = 0
    holds: int = 0
    controllers: list[PickController] = field(default_factory=list)

    @property
    def success_rate(self) -> float:
        return sum(t["success"] for t in self.tasks) / len(self.tasks) if self.tasks else 0.0


def run_ideal(sc: Scenario, delay_us: int = 0, frame_loss: float = 0.0, world: World | None = None,
              pose_error_sd_m: float | None = None) -> IdealLoopResult:
    """Run ``sc`` for its duration; each camera frame is lost with probability ``frame_loss``,
    the others reach the controller ``delay_us`` after capture. With ``pose_error_sd_m`` the
    poses are tracked estimates (error of that sd per axis) instead of exact ground truth."""
    if not 0.0 <= frame_loss < 1.0:
        raise ValueError(f"frame_loss must be in [0, 1), got {frame_loss}")
    if delay_us < 0:
        raise ValueError(f"delay_us must be >= 0, got {delay_us}")
    world = world or World(sc)
    step = sc.physics_timestep_us
    ctls = [PickController(sc.robot, sc.work_cell.object_size_m, SERVO_LAG_S) for _ in range(sc.loops)]
    loss_rngs = [rng(sc.seed, f"ideal/frame-loss-c{i}") for i in range(sc.loops)]
    error_rngs = [rng(sc.seed, f"ideal/pose-error-c{i}") for i in range(sc.loops)]
    trackers = [Tracker((sc.work_cell.belt_speed_m_s, 0.0, 0.0)) for _ in range(sc.loops)]
    # One time-ordered queue of everything that happens: (t_us, order, seq, kind, payload).
    queue: list[tuple[int, int, int, str, Any]] = []
    seq = 0

    def push(t: int, order: int, kind: str, payload: Any) -> None:
        nonlocal seq
        heapq.heappush(queue, (t, order, seq, kind, payload))
        seq += 1

    for i in range(sc.loops):
        for at, part in spawn_plan(sc, rng(sc.seed, f"physics/spawn-c{i}"), step):
            push(at, 0, "spawn", (i, part))
        push(frame_offset_us(i, sc.loops, sc.frame_period_us, step), 1, "frame", i)
    push(0, 3, "tick", None)
    res = IdealLoopResult(tasks=[], controllers=ctls)
    end = sc.duration_us
    while queue and queue[0][0] < end:
        t, _, _, kind, payload = heapq.heappop(queue)
        world.advance_to(t)
        if kind == "spawn":
            world.spawn(payload[0], **payload[1])
        elif kind == "frame":
            i = payload
            res.frames += 1
            if loss_rngs[i].random() >= frame_loss:
                objects = world.objects(i)
                if pose_error_sd_m is None:
                    tracks = [{"id": o["task_id"], "t_us": t, "p": o["p"], "v": o["v"]} for o in objects]
                else:
                    trackers[i].update(t, [np.asarray(o["p"]) + error_rngs[i].normal(0.0, pose_error_sd_m, 3)
                                           for o in objects])
                    tracks = trackers[i].report(g.BELT_HALF_WIDTH)
                push(t + delay_us, 2, "pose", (i, tracks))
            push(t + sc.frame_period_us, 1, "frame", i)
        elif kind == "pose":
            res.frames_delivered += 1
            ctls[payload[0]].on_estimate(payload[1])
        elif kind == "state":
            for i, (q, gripped) in enumerate(payload):
                ctls[i].on_state(q, gripped)
        elif kind == "tick":
            # The drives' state as published now reaches the controllers after the state latency.
            states = [(st["q"], st["gripped"]) for st in (world.joint_state(i) for i in range(sc.loops))]
            push(t + sc.robot.state_latency_us, 2, "state", states)
            for i, ctl in enumerate(ctls):
                q, suction = ctl.step(t)
                push(t + sc.robot.actuation_latency_us, 2, "command", (i, [float(v) for v in q], suction))
            push(t + sc.robot.control_period_us, 3, "tick", None)
        elif kind == "command":
            world.command(*payload)
    world.advance_to(end)
    res.tasks = [r for r in world.finish() if r["outcome"] != "unfinished"]
    res.holds = sum(c.holds for c in ctls)
    return res
