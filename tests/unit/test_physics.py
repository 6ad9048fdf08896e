"""The MuJoCo hall: models compile and step without warnings; the controller picks reliably."""

from __future__ import annotations

import mujoco
import numpy as np
import pytest

from services.common.scenario import parse_scenario
from services.physics.scene import SERVO_LAG_S, build_mjcf
from services.physics.world import World
from services.robot.controller import PickController


@pytest.mark.parametrize("loops", [1, 4])
def test_hall_compiles_and_steps_10_s_without_warnings(loops: int) -> None:
    sc = parse_scenario({"loops": loops})
    model = mujoco.MjModel.from_xml_string(build_mjcf(sc))
    data = mujoco.MjData(model)
    for _ in range(int(10 / model.opt.timestep)):
        mujoco.mj_step(model, data)
    assert all(w.number == 0 for w in data.warning), [w.number for w in data.warning]
    assert np.isfinite(data.qpos).all()


def pick_run(delay_us: int, compensation: bool, seconds: float = 26.0) -> list[dict]:
    """Ground-truth poses every frame, delivered ``delay_us`` late, to the real controller."""
    sc = parse_scenario({"loops": 1, "robot": {"delay_compensation": compensation}})
    world = World(sc)
    ctl = PickController(sc.robot, sc.cell.object_size_m, SERVO_LAG_S)
    period = int(sc.cell.object_period_s * 1e6)
    next_spawn, pending = 500_000, []
    for k in range(1, int(seconds * 1000) + 1):
        t = k * 1000
        world.advance_to(t)
        if t >= next_spawn:
            world.spawn(0)
            next_spawn += period
        if t % sc.frame_period_us < 1000:
            tracks = [{"id": o["task_id"], "t_us": t, "p": o["p"], "v": o["v"]} for o in world.objects(0)]
            pending.append((t + delay_us, tracks))
        while pending and pending[0][0] <= t:
            ctl.on_estimate(pending.pop(0)[1])
        if t % sc.robot.control_period_us == 0:
            st = world.joint_state(0)
            ctl.on_state(st["q"], st["gripped"])
            q, suction = ctl.step(t)
            world.command(0, list(q), suction)
    return [r for r in world.finish() if r["outcome"] != "unfinished"]


def test_controller_places_every_part_with_ideal_poses() -> None:
    tasks = pick_run(0, True)
    assert len(tasks) >= 5
    assert all(t["outcome"] == "placed" for t in tasks), tasks


def test_delay_compensation_matters_for_stale_poses() -> None:
    compensated = pick_run(200_000, True)
    naive = pick_run(200_000, False)
    placed = [sum(t["success"] for t in r) / len(r) for r in (compensated, naive)]
    assert placed[0] == 1.0 and placed[1] < placed[0]
