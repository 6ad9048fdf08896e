"""Offline rendering of a working cell: parts arrive by the scenario's spawn plan and the real
pick controller, fed ground-truth poses with no network between, picks them, so frames show what
a run's camera sees; for frame measurements and the pose estimator's data sets
(docs/perception.md)."""

from __future__ import annotations

from collections.abc import Iterator

import numpy as np

from domain.arm import SERVO_LAG_S
from domain.controller import PickController
from domain.world import World, spawn_plan
from scenario.schema import Scenario


def working_cell(sc: Scenario, spawn_rng: np.random.Generator, frame_times_us: list[int],
                 world: World | None = None, cell: int = 0) -> Iterator[tuple[int, World]]:
    """Advance cell ``cell`` of ``world`` (a new World of ``sc`` by default) through the run, its
    parts drawn from ``spawn_rng``, and yield (t_us, world) at each of ``frame_times_us`` (us,
    ascending), ready to render."""
    world = world or World(sc)
    step = sc.physics_timestep_us
    ctl = PickController(sc.robot, sc.work_cell.object_size_m, SERVO_LAG_S)
    spawns = spawn_plan(sc, spawn_rng, step)
    k_spawn = 0
    t_ctl = 0
    t_est = 0
    for t_frame in frame_times_us:
        while True:
            t_next = min(t_ctl, t_est, spawns[k_spawn][0] if k_spawn < len(spawns) else t_frame + 1)
            if t_next > t_frame:
                break
            world.advance_to(t_next)
            if k_spawn < len(spawns) and spawns[k_spawn][0] == t_next:
                world.spawn(cell, **spawns[k_spawn][1])
                k_spawn += 1
            elif t_est == t_next:
                ctl.on_estimate([{"id": o["task_id"], "t_us": t_next, "p": o["p"], "v": o["v"]}
                                 for o in world.objects(cell)])
                t_est += sc.frame_period_us
            else:
                st = world.joint_state(cell)
                ctl.on_state(st["q"], st["gripped"])
                q, suction = ctl.step(t_next)
                world.command(cell, [float(v) for v in q], suction)
                t_ctl += sc.robot.control_period_us
        world.advance_to(t_frame)
        yield t_frame, world
