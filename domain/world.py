"""The factory hall in MuJoCo (``World``): stepping in fixed ``physics_timestep_us`` steps, the
conveyor drive, commands, spawns, task checks, observations and RGB-D of the detailed cells.
Times are integer microseconds; the state at a time does not depend on how the advance to it
is split (docs/physics.md)."""

from __future__ import annotations

from typing import Any

import mujoco
import numpy as np

from domain import part_pool
from domain.arm import HOME_Q, JOINTS, N_JOINTS
from domain.cell_camera import CellCamera
from domain.cell_state import CellState, index_cells
from domain.conveyor import OFFSETS, LooseParts, loose_parts, on_belts
from domain.hall import build_model, object_pool_size
from domain.part_pool import spawn_plan
from domain.snapshots import HeldStates, Snapshot, observed
from domain.suction import release, seal_slot, weld
from domain.task_outcomes import Task, judge
from fabric import metrics
from scenario.schema import Scenario
from wire.bodies import ArmState, Part

__all__ = ["CHECK_PERIOD_US", "CellState", "Snapshot", "Task", "World", "spawn_plan"]

CHECK_PERIOD_US = 10_000  # which parts ride the belt, and task outcomes, are checked this often


class World:
    """All N cells of the hall in one MuJoCo model."""

    def __init__(self, scenario: Scenario) -> None:
        """The hall of ``scenario`` at time 0: arms at home, every pool part parked."""
        self.sc = scenario
        self.model = build_model(scenario)
        self.data = mujoco.MjData(self.model)
        self.dt_us = scenario.physics_timestep_us
        self.t_us = 0
        self.size = scenario.work_cell.object_size_m
        self.mass = scenario.work_cell.object_mass_kg
        self.pool = object_pool_size(scenario)
        self.tasks: list[Task] = []
        self.cells: list[CellState] = index_cells(self.model, scenario, self.pool, self.size)
        for c in self.cells:
            self.data.qpos[c.qadr] = HOME_Q
            self.data.ctrl[c.act] = HOME_Q
            for slot in range(self.pool):
                part_pool.may_sleep(self.model, c, slot, True)
        mujoco.mj_forward(self.model, self.data)
        # Each arm's servo range, gathered once: commands come 100 times a simulated second an arm.
        self._ctrl_range = [(self.model.actuator_ctrlrange[c.act, 0].copy(),
                             self.model.actuator_ctrlrange[c.act, 1].copy()) for c in self.cells]
        self._camera = CellCamera(self.model)
        self._loose: LooseParts | None = None
        self._on_belt: np.ndarray | None = None  # dof addresses of the parts the belt carries
        self._check_steps = max(1, CHECK_PERIOD_US // self.dt_us)
        self._steps = 0
        self._vacuum: list[CellState] = []  # cells whose valve is open with nothing held
        self._held = HeldStates(self.dt_us)

    # ---- stepping ---------------------------------------------------------------------------
    def advance_to(self, t_us: int) -> None:
        """Step until the next step would pass ``t_us`` (us)."""
        while self.t_us + self.dt_us <= t_us:
            self.before_step()
            mujoco.mj_step(self.model, self.data)
            self.after_step()

    def before_step(self) -> None:
        """What a step begins with, before ``mj_step``: the conveyor drive. (A step may run its
        ``mj_step`` elsewhere, e.g. in a thread: ``before_step``, ``mj_step``, ``after_step``.)"""
        if self._on_belt is None or self._steps % self._check_steps == 0:
            self._on_belt = on_belts(self.data.qpos, self._loose_parts())
        if self._on_belt.size:  # belt speed along x, nothing across
            self.data.qvel[self._on_belt] = self.sc.work_cell.belt_speed_m_s
            self.data.qvel[self._on_belt + 1] = 0.0

    def after_step(self) -> None:
        """What a step ends with, after ``mj_step``: the clock, suction seals and task outcomes."""
        self.t_us += self.dt_us
        self._steps += 1
        for c in self._vacuum:  # cups with the valve open and nothing held yet
            if c.active:
                slot = seal_slot(self.data, c)
                if slot is not None:
                    self._grip(c, slot)
        if self._steps % self._check_steps == 0:
            self._check_tasks()

    def after_steps(self, steps: int) -> None:
        """What ``steps`` steps handed over at once end with: the clock, and the last step's
        seals and task checks (the ones before it had none: ``steps_alone``)."""
        self.t_us += (steps - 1) * self.dt_us
        self._steps += steps - 1
        self.after_step()

    def steps_alone(self) -> int:
        """How many steps from now may run with nothing in Python between them: one while a cup
        waits to seal on a part (checked after every step), else up to the next task check, which
        also picks the parts the belt drives (``belt_drive``)."""
        if self._vacuum:
            return 1
        return self._check_steps - self._steps % self._check_steps

    def belt_drive(self) -> tuple[np.ndarray, float]:
        """What ``before_step`` sets (after it has run): dof addresses of the parts on a belt
        (int64), whose velocity becomes the belt speed along x and 0 across, and that speed
        (m/s)."""
        on_belt = self._on_belt
        assert on_belt is not None, "belt_drive before before_step"
        return np.ascontiguousarray(on_belt, dtype=np.int64), float(self.sc.work_cell.belt_speed_m_s)

    # ---- observations held while steps run elsewhere ----------------------------------------
    def hold_observations(self) -> None:
        """Until ``release_observations``, observations show the state as it is now, while a step
        runs elsewhere (called before ``before_step``, whose belt drive sets velocities); it is
        kept for ``observe_at`` any time in this step, also once later steps have run."""
        self._held.hold(self.t_us, (self.data.qpos.copy(), self.data.qvel.copy(),
                                    [observed(c) for c in self.cells]))

    def hold_ahead(self, steps: int) -> tuple[np.ndarray, np.ndarray]:
        """For ``steps`` steps handed over at once (``steps_alone``), after ``hold_observations``
        and ``before_step``: the rows (steps - 1, nq) and (steps - 1, nv) into which the stepping
        thread copies qpos and qvel at the start of each step after the first (before its belt
        drive), held for the observers of those steps. The parts in play do not change within."""
        return self._held.hold_ahead(self.t_us, steps, self.model.nq, self.model.nv)

    def release_observations(self) -> None:
        """Observations show the live state again (the step that ran elsewhere has ended)."""
        self._held.release()

    def observe_at(self, t_us: int) -> None:
        """Observations show the state at ``t_us`` (us): the held one of the step it falls in, or
        the live one if the world is at that step. Observations come in time order, so the
        snapshots of earlier steps are dropped."""
        self._held.observe_at(t_us, self.t_us)

    # ---- parts in play ----------------------------------------------------------------------
    def _loose_parts(self) -> LooseParts:
        """Parts in play and not held by a cup; rebuilt only when a part spawns, ends, is gripped
        or released, so that the per-step work is a few vectorised numpy operations."""
        if self._loose is None:
            self._loose = loose_parts(self.cells)
        return self._loose

    def _changed(self, c: CellState) -> None:
        """A part of ``c`` spawned, ended, was gripped or released: rebuild the per-step index and
        the cell's view."""
        self._loose = None
        self._on_belt = None
        c.view = None

    def _check_tasks(self) -> None:
        rows, tasks, qa, va, origin, half = self._loose_parts()
        if not rows:
            return
        p = self.data.qpos[qa] - origin
        speed = np.linalg.norm(self.data.qvel[va[:, None] + OFFSETS], axis=1)
        for k, outcome, reason in judge(tasks, p, speed, half, self.t_us):
            self._end(*rows[k], outcome, reason)

    def _end(self, c: CellState, slot: int, outcome: str, reason: str) -> None:
        task = c.active.pop(slot)
        task.end_us, task.outcome, task.reason = self.t_us, outcome, reason
        metrics.TASKS.labels(outcome).inc()
        part_pool.park(self.model, self.data, c, slot)
        c.free_slots.append(slot)
        self._changed(c)

    # ---- commands ---------------------------------------------------------------------------
    def spawn(self, cell: int, y_offset_m: float = 0.0, yaw_rad: float = 0.0,
              size_m: float | None = None, mass_kg: float | None = None) -> Task | None:
        """Put a part on the upstream end of the belt of cell ``cell`` (None if the pool is
        empty), ``y_offset_m`` (m) off the belt's axis, turned ``yaw_rad`` (rad) about z, a cube
        of edge ``size_m`` (m) and mass ``mass_kg`` (kg), by default the scenario's nominal part."""
        c = self.cells[cell]
        if not c.free_slots:
            c.skipped_spawns += 1
            return None
        size = self.size if size_m is None else float(size_m)
        mass = self.mass if mass_kg is None else float(mass_kg)
        slot = c.free_slots.pop(0)
        part_pool.place(self.model, self.data, c, slot, y_offset_m, yaw_rad, size, mass,
                        self.sc.work_cell.belt_speed_m_s)
        task = Task(cell=cell, task_id=c.tasks_spawned, slot=slot, spawn_us=self.t_us,
                    size_m=size, mass_kg=mass, yaw_rad=float(yaw_rad))
        c.tasks_spawned += 1
        c.active[slot] = task
        self.tasks.append(task)
        self._changed(c)
        return task

    def command(self, cell: int, q_target: list[float], suction: bool) -> None:
        """Set the six joint servo targets ``q_target`` (rad, clipped to the servos' range) and
        the suction valve (open if ``suction``) of cell ``cell``."""
        if not 0 <= cell < len(self.cells):  # a negative index would command another cell
            raise ValueError(f"command for work cell {cell}: the hall has work cells 0..{len(self.cells) - 1}")
        c = self.cells[cell]
        if len(q_target) != N_JOINTS:
            raise ValueError(f"cell {cell}: command has {len(q_target)} joint targets, the arm has "
                             f"{N_JOINTS} ({', '.join(JOINTS)})")
        q = np.asarray(q_target, dtype=float)
        if not np.isfinite(q).all():  # NaN in one cell's controls disturbs every cell's solve
            raise ValueError(f"cell {cell}: command has a non-finite joint target: {list(q_target)}")
        lo, hi = self._ctrl_range[cell]
        # np.clip's result (elementwise max, then min) without its dispatch
        self.data.ctrl[c.act] = np.minimum(np.maximum(q, lo), hi)
        if suction and not c.suction:
            # Each opening of the valve is one grasp attempt, on the part the cup is over (the
            # nearest on the floor plan of those not grasped yet).
            tip, xpos = self.data.site_xpos[c.tcp], self.data.xpos

            def off(slot: int) -> float:
                p = xpos[c.obj_body[slot]]
                return float((p[0] - tip[0]) ** 2 + (p[1] - tip[1]) ** 2)

            waiting = [slot for slot, task in c.active.items() if task.grasp_us is None]
            if waiting:
                c.active[min(waiting, key=off)].grasp_attempts += 1
        c.suction = suction
        if suction and c.gripped is None:
            slot = seal_slot(self.data, c)
            if slot is not None:
                self._grip(c, slot)
        elif not suction and c.gripped is not None:
            release(self.model, self.data, c)
            self._changed(c)
        # Only this cell can have joined or left the open cups (``_grip`` removes the others):
        # rebuilt in cell order when it has, so a tick of N commands stays O(N).
        if (c.suction and c.gripped is None) != any(x is c for x in self._vacuum):
            self._vacuum = [x for x in self.cells if x.suction and x.gripped is None]

    def _grip(self, c: CellState, slot: int) -> None:
        """The cup of ``c`` has sealed on part ``slot``: weld it there."""
        weld(self.model, self.data, c, slot)
        task = c.active[slot]
        task.grasp_us = task.grasp_us or self.t_us
        self._vacuum = [x for x in self._vacuum if x is not c]
        self._changed(c)

    # ---- observation ------------------------------------------------------------------------
    def joint_state(self, cell: int) -> ArmState:
        """Joint positions ``q`` (rad, six) of cell ``cell``'s arm and whether its cup holds a
        part (``gripped``), as observations show them."""
        c, seen = self.cells[cell], self._held.seen
        if seen is None:
            return {"q": [float(v) for v in self.data.qpos[c.qadr]], "gripped": c.gripped is not None}
        return {"q": [float(v) for v in seen[0][c.qadr]], "gripped": seen[2][cell][0]}

    def objects(self, cell: int) -> list[Part]:
        """Ground truth of the parts in play in cell ``cell``, by task id: position ``p`` (m, cell
        frame), velocity ``v`` (m/s) and ``gripped``, as observations show them."""
        c, seen = self.cells[cell], self._held.seen
        qpos, qvel, view = (self.data.qpos, self.data.qvel, observed(c)) if seen is None else \
            (seen[0], seen[1], seen[2][cell])
        return [{"task_id": task_id, "p": [float(v) for v in qpos[a:a + 3] - c.origin],
                 "v": [float(v) for v in qvel[va:va + 3]], "gripped": held}
                for task_id, a, va, held in view[1]]

    def render(self, cell: int, width: int, height: int, camera: str = "camera",
               depth: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """RGB (uint8 HxWx3) and, if ``depth``, depth (float32 metres along the optical axis) from
        camera ``camera`` of cell ``cell``, ``width`` x ``height`` px."""
        return self._camera.render(self.data, cell, width, height, camera, depth)

    # ---- task rows --------------------------------------------------------------------------
    def take_ended(self, upto_us: int) -> list[dict[str, Any]]:
        """Rows of the tasks that ended by ``upto_us`` (us) since the last call, which ``tasks``
        then forgets: a long run keeps only the tasks in play (``finish`` gives the rest). The
        bound keeps the rows' order independent of how far a step ahead had got."""
        ended = [t for t in self.tasks if t.end_us is not None and t.end_us <= upto_us]
        if ended:
            self.tasks = [t for t in self.tasks if t.end_us is None or t.end_us > upto_us]
        return [t.row() for t in ended]

    def finish(self) -> list[dict[str, Any]]:
        """Close open tasks as unfinished; the rows of every task not taken by ``take_ended``."""
        for c in self.cells:
            for task in c.active.values():
                task.outcome, task.reason, task.end_us = "unfinished", "run ended", self.t_us
        self.close()
        return [t.row() for t in self.tasks]

    def close(self) -> None:
        """Release the renderer. Its GL context belongs to the thread that rendered: call this
        there (a renderer left to the garbage collector fails on another thread)."""
        self._camera.close()
