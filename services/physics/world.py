"""The factory hall in MuJoCo: stepping, conveyor drive, suction grip, object spawns, task outcomes
and RGB-D rendering of the detailed cells.

Time is integer microseconds; the world steps in fixed ``physics_timestep_us`` steps so the state
at any time is the same however the caller splits the advance (windows, events).
"""

from __future__ import annotations

import os
from dataclasses import dataclass, field
from typing import Any

import numpy as np

os.environ.setdefault("MUJOCO_GL", "egl")
import mujoco  # noqa: E402  (MUJOCO_GL must be set before import)

from services.common.scenario import Scenario  # noqa: E402
from services.physics import cell_geometry as g  # noqa: E402
from services.physics.scene import OBJECT_POOL, build_mjcf  # noqa: E402

SEAL_DISTANCE_M = 0.012  # cup tip within this of the part's top face seals the suction
SETTLE_SPEED_M_S = 0.02  # a part slower than this counts as resting
SETTLE_TIME_US = 200_000  # resting this long on the platform makes the task a success
FALLEN_Z_M = 0.5  # below this a part has left the belt/platform: task over


@dataclass
class Task:
    """One object's life: spawned on the belt, then placed, missed or dropped."""

    cell: int
    task_id: int
    slot: int
    spawn_us: int
    grasp_us: int | None = None
    grasp_attempts: int = 0
    end_us: int | None = None
    outcome: str | None = None  # placed | missed | dropped | unfinished
    reason: str = ""
    resting_since_us: int | None = None

    def row(self) -> dict[str, Any]:
        return {
            "cell": self.cell, "task_id": self.task_id, "spawn_us": self.spawn_us,
            "grasp_us": self.grasp_us, "grasp_attempts": self.grasp_attempts,
            "end_us": self.end_us, "outcome": self.outcome, "success": self.outcome == "placed",
            "reason": self.reason,
        }


@dataclass
class CellState:
    index: int
    origin: np.ndarray
    qadr: np.ndarray  # qpos addresses of the x, y, z joints
    vadr: np.ndarray
    act: np.ndarray  # actuator ids x, y, z
    obj_body: list[int]
    obj_qadr: list[int]
    obj_vadr: list[int]
    eq: list[int]
    free_slots: list[int] = field(default_factory=list)
    active: dict[int, Task] = field(default_factory=dict)  # slot -> task
    suction: bool = False
    gripped: int | None = None  # slot held by the cup
    tasks_spawned: int = 0
    skipped_spawns: int = 0


class World:
    """All N cells of the hall in one MuJoCo model."""

    def __init__(self, scenario: Scenario, render_cells: list[int] | None = None) -> None:
        self.sc = scenario
        self.model = mujoco.MjModel.from_xml_string(build_mjcf(scenario))
        self.data = mujoco.MjData(self.model)
        self.dt_us = scenario.physics_timestep_us
        self.t_us = 0
        self.size = scenario.cell.object_size_m
        self.tasks: list[Task] = []
        m = self.model
        self.cells: list[CellState] = []
        origins = scenario.hall.cell_origins(scenario.loops)
        for i, (x, y) in enumerate(origins):
            def jid(name: str) -> int:
                return mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_JOINT, name)

            joints = [jid(f"c{i}_{a}") for a in "xyz"]
            objs = [mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"c{i}_obj{k}") for k in range(OBJECT_POOL)]
            frees = [jid(f"c{i}_obj{k}_free") for k in range(OBJECT_POOL)]
            self.cells.append(CellState(
                index=i, origin=np.array([x, y, 0.0]),
                qadr=np.array([m.jnt_qposadr[j] for j in joints]),
                vadr=np.array([m.jnt_dofadr[j] for j in joints]),
                act=np.array([mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_ACTUATOR, f"c{i}_{a}_servo") for a in "xyz"]),
                obj_body=objs,
                obj_qadr=[m.jnt_qposadr[j] for j in frees],
                obj_vadr=[m.jnt_dofadr[j] for j in frees],
                eq=[mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_EQUALITY, f"c{i}_grip{k}") for k in range(OBJECT_POOL)],
                free_slots=list(range(OBJECT_POOL)),
            ))
        home = g.joints_for_tool([0.0, 0.0, 1.05])
        for c in self.cells:
            self.data.qpos[c.qadr] = home
            self.data.ctrl[c.act] = home
        mujoco.mj_forward(m, self.data)
        self._renderer: Any = None
        self._render_cells = render_cells or []

    # ---- stepping ---------------------------------------------------------------------------
    def advance_to(self, t_us: int) -> None:
        """Step until the next step would pass ``t_us``."""
        while self.t_us + self.dt_us <= t_us:
            self._drive_belts()
            mujoco.mj_step(self.model, self.data)
            self.t_us += self.dt_us
            self._check_tasks()

    def _obj_pos(self, c: CellState, slot: int) -> np.ndarray:
        a = c.obj_qadr[slot]
        return self.data.qpos[a:a + 3] - c.origin

    def _drive_belts(self) -> None:
        v = self.sc.cell.belt_speed_m_s
        h = self.size / 2
        qvel = self.data.qvel
        for c in self.cells:
            for slot in c.active:
                if c.gripped == slot:
                    continue
                p = self._obj_pos(c, slot)
                on_belt = (abs(p[0]) <= g.BELT_HALF_LENGTH and abs(p[1]) <= g.BELT_HALF_WIDTH
                           and p[2] <= g.BELT_TOP_Z + h + 0.004)
                if on_belt:
                    va = c.obj_vadr[slot]
                    qvel[va] = v
                    qvel[va + 1] = 0.0

    def _check_tasks(self) -> None:
        h = self.size / 2
        for c in self.cells:
            for slot, task in list(c.active.items()):
                if c.gripped == slot:
                    task.resting_since_us = None
                    continue
                p = self._obj_pos(c, slot)
                if p[2] < FALLEN_Z_M:
                    self._end(c, slot, "dropped" if task.grasp_us is not None else "missed",
                              "fell off the belt end" if task.grasp_us is None else "released away from the platform")
                    continue
                px, py = g.PLATFORM_CENTRE
                on_platform = (abs(p[0] - px) <= g.PLATFORM_HALF and abs(p[1] - py) <= g.PLATFORM_HALF
                               and p[2] <= g.PLATFORM_TOP_Z + h + 0.01)
                va = c.obj_vadr[slot]
                speed = float(np.linalg.norm(self.data.qvel[va:va + 3]))
                if on_platform and speed < SETTLE_SPEED_M_S:
                    if task.resting_since_us is None:
                        task.resting_since_us = self.t_us
                    elif self.t_us - task.resting_since_us >= SETTLE_TIME_US:
                        self._end(c, slot, "placed", "resting on the platform")
                else:
                    task.resting_since_us = None

    def _end(self, c: CellState, slot: int, outcome: str, reason: str) -> None:
        task = c.active.pop(slot)
        task.end_us, task.outcome, task.reason = self.t_us, outcome, reason
        self._park(c, slot)
        c.free_slots.append(slot)

    def _park(self, c: CellState, slot: int) -> None:
        a, va = c.obj_qadr[slot], c.obj_vadr[slot]
        self.data.qpos[a:a + 3] = c.origin + np.array([-0.3 + 0.2 * slot, -1.6, self.size / 2 + 0.001])
        self.data.qpos[a + 3:a + 7] = [1, 0, 0, 0]
        self.data.qvel[va:va + 6] = 0.0

    # ---- commands ---------------------------------------------------------------------------
    def spawn(self, cell: int, y_offset_m: float = 0.0, yaw_rad: float = 0.0) -> Task | None:
        """Put a part on the upstream end of the belt of ``cell`` (None if the pool is empty)."""
        c = self.cells[cell]
        if not c.free_slots:
            c.skipped_spawns += 1
            return None
        slot = c.free_slots.pop(0)
        a, va = c.obj_qadr[slot], c.obj_vadr[slot]
        self.data.qpos[a:a + 3] = c.origin + np.array([g.SPAWN_X, y_offset_m, g.BELT_TOP_Z + self.size / 2 + 0.001])
        self.data.qpos[a + 3:a + 7] = [np.cos(yaw_rad / 2), 0, 0, np.sin(yaw_rad / 2)]
        self.data.qvel[va:va + 6] = 0.0
        self.data.qvel[va] = self.sc.cell.belt_speed_m_s
        task = Task(cell=cell, task_id=c.tasks_spawned, slot=slot, spawn_us=self.t_us)
        c.tasks_spawned += 1
        c.active[slot] = task
        self.tasks.append(task)
        return task

    def command(self, cell: int, q_target: list[float], suction: bool) -> None:
        """Set the gantry servo targets and the suction valve of ``cell``."""
        c = self.cells[cell]
        lo = self.model.actuator_ctrlrange[c.act, 0]
        hi = self.model.actuator_ctrlrange[c.act, 1]
        self.data.ctrl[c.act] = np.clip(np.asarray(q_target, dtype=float), lo, hi)
        if suction and not c.suction:
            for task in c.active.values():  # each opening of the valve is one grasp attempt
                if task.grasp_us is None:
                    task.grasp_attempts += 1
                    break
        if suction and c.gripped is None:
            self._try_seal(c)
        elif not suction and c.gripped is not None:
            self.data.eq_active[c.eq[c.gripped]] = 0
            c.gripped = None
        c.suction = suction

    def _try_seal(self, c: CellState) -> None:
        tip = g.tool_position(self.data.qpos[c.qadr])
        h = self.size / 2
        for slot, task in c.active.items():
            p = self._obj_pos(c, slot)
            top = p[2] + h
            if abs(tip[0] - p[0]) <= h and abs(tip[1] - p[1]) <= h and -0.003 <= tip[2] - top <= SEAL_DISTANCE_M:
                self._weld(c, slot)
                task.grasp_us = task.grasp_us or self.t_us
                return

    def _weld(self, c: CellState, slot: int) -> None:
        """Activate the grip weld, holding the part at its current pose relative to the cup."""
        m, d = self.model, self.data
        cup = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"c{c.index}_cup")
        obj = c.obj_body[slot]
        eq = c.eq[slot]
        r1 = d.xmat[cup].reshape(3, 3)
        rel_pos = r1.T @ (d.xpos[obj] - d.xpos[cup])
        q1_inv = np.zeros(4)
        mujoco.mju_negQuat(q1_inv, d.xquat[cup])
        rel_quat = np.zeros(4)
        mujoco.mju_mulQuat(rel_quat, q1_inv, d.xquat[obj])
        m.eq_data[eq, 0:3] = 0.0
        m.eq_data[eq, 3:6] = rel_pos
        m.eq_data[eq, 6:10] = rel_quat
        m.eq_data[eq, 10] = 1.0
        d.eq_active[eq] = 1
        c.gripped = slot

    # ---- observation ------------------------------------------------------------------------
    def joint_state(self, cell: int) -> dict[str, Any]:
        c = self.cells[cell]
        return {"q": [float(v) for v in self.data.qpos[c.qadr]],
                "gripped": c.gripped is not None}

    def objects(self, cell: int) -> list[dict[str, Any]]:
        """Ground truth of the parts on the belt of ``cell`` (cell frame), by task id."""
        c = self.cells[cell]
        out = []
        for slot, task in sorted(c.active.items(), key=lambda kv: kv[1].task_id):
            va = c.obj_vadr[slot]
            out.append({"task_id": task.task_id, "p": [float(v) for v in self._obj_pos(c, slot)],
                        "v": [float(v) for v in self.data.qvel[va:va + 3]],
                        "gripped": c.gripped == slot})
        return out

    def render(self, cell: int, width: int, height: int, camera: str = "camera",
               depth: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """RGB (uint8 HxWx3) and depth (float32 metres along the optical axis) from a cell camera."""
        if self._renderer is None or self._renderer.width != width or self._renderer.height != height:
            if self._renderer is not None:
                self._renderer.close()
            self._renderer = mujoco.Renderer(self.model, height, width)
        r = self._renderer
        r.disable_depth_rendering()
        r.update_scene(self.data, camera=f"c{cell}_{camera}")
        rgb = r.render().copy()
        dep = None
        if depth:
            r.enable_depth_rendering()
            r.update_scene(self.data, camera=f"c{cell}_{camera}")
            dep = r.render().copy()
            r.disable_depth_rendering()
        return rgb, dep

    def finish(self) -> list[dict[str, Any]]:
        """Close open tasks as unfinished; all task rows."""
        for c in self.cells:
            for task in c.active.values():
                task.outcome, task.reason, task.end_us = "unfinished", "run ended", self.t_us
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
        return [t.row() for t in self.tasks]
