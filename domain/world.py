"""The factory hall in MuJoCo: stepping, conveyor drive, suction grip, object spawns, task outcomes
and RGB-D rendering of the detailed cells.

Time is integer microseconds; the world steps in fixed ``physics_timestep_us`` steps so the state
at any time is the same however the caller splits the advance (windows, events).

Suction. The cup is a bellows vacuum cup; when the valve is open and the cup's lip is on a part's
upward face (within the bellows' stroke above it, lip not overhanging), the part is held by a
weld equality activated at the part's current pose relative to the cup, and let go the moment
the valve closes. A weld is the standard way to model vacuum grip in a rigid-body simulator:
modelling the seal and the pressure force would need a soft lip and a fluid model and would
change no outcome we measure, since a sealed cup holds these parts far below its rated force;
what matters for the study (whether and when the cup reaches the part) is decided by the
seal condition, which is geometric and strict.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any

import mujoco
import numpy as np

from domain import work_cell as g
from domain.arm import CUP_BODY, CUP_RADIUS_M, HOME_Q, JOINTS, N_JOINTS, TCP_SITE
from domain.hall import build_model, object_pool_size, park_position
from fabric import metrics
from scenario.schema import Scenario

SEAL_DISTANCE_M = 0.012  # bellows stroke: the lip seals from this high above the face ...
SEAL_PRESS_M = 0.004  # ... down to this far below it (bellows compressed)
SEAL_LIP_COMPLIANCE_M = 0.005  # the lip may overhang the face edge by this much and still seal
SEAL_MAX_TILT = math.radians(20)  # face normal and cup axis must agree within this
SETTLE_SPEED_M_S = 0.02  # a part slower than this counts as resting
SETTLE_TIME_US = 200_000  # resting this long on the platform makes the task a success
FALLEN_Z_M = 0.5  # below this a part has left the belt/platform: task over
ON_BELT_SLACK_M = 0.004  # a part's centre this close above resting height rides the belt
GRIPPED_CONTYPE = 4  # a held part stops colliding with the cup and arm (the weld holds it)
CHECK_PERIOD_US = 10_000  # which parts ride the belt, and task outcomes, are checked this often
_OFFSETS = np.arange(3)
# What observations read of one step (``World.hold_observations``): qpos, qvel, each cell's view.
Snapshot = tuple[np.ndarray, np.ndarray, list[tuple[bool, tuple[tuple[int, int, int, bool], ...]]]]
# Sleep policies of a kinematic tree (mjtSleepPolicy): see ``World._may_sleep``.
SLEEP_NEVER = int(mujoco.mjtSleepPolicy.mjSLEEP_NEVER)
SLEEP_ALLOWED = int(mujoco.mjtSleepPolicy.mjSLEEP_ALLOWED)
# A geom in this group is not drawn (MjvOption shows groups 0-2 by default): where rendering
# leaves out the other cells, their geoms sit in it for the duration of the render.
HIDDEN_GROUP = 5
CAMERA_DOWN_COS = 0.99  # a cell camera counts as looking straight down within ~8 degrees


def spawn_plan(sc: Scenario, rng: np.random.Generator, step_us: int) -> list[tuple[int, dict[str, float]]]:
    """When and which parts one cell's belt receives over the run: (time us, ``World.spawn``
    keyword arguments), on the physics step grid. Spawn jitter, lateral offset, yaw, size and
    mass are drawn from ``rng`` (a spread of 0 draws nothing, so adding a spread to a scenario
    leaves the other draws of the stream unchanged)."""
    cfg = sc.work_cell
    period = int(cfg.object_period_s * 1e6)
    jitter = int(cfg.object_jitter_s * 1e6)
    plan = []
    t = int(cfg.first_object_s * 1e6)
    while t < sc.duration_us:
        dt = int(rng.integers(-jitter, jitter + 1)) if jitter else 0
        at = max(0, (t + dt) // step_us * step_us)
        kw = {"y_offset_m": float(rng.uniform(-cfg.object_lateral_spread_m, cfg.object_lateral_spread_m))}
        if cfg.object_yaw_spread_deg:
            kw["yaw_rad"] = math.radians(float(rng.uniform(-cfg.object_yaw_spread_deg, cfg.object_yaw_spread_deg)))
        if cfg.object_size_spread_m:
            kw["size_m"] = cfg.object_size_m + float(rng.uniform(-cfg.object_size_spread_m, cfg.object_size_spread_m))
        if cfg.object_mass_spread_kg:
            kw["mass_kg"] = cfg.object_mass_kg + float(rng.uniform(-cfg.object_mass_spread_kg, cfg.object_mass_spread_kg))
        plan.append((at, kw))
        t += period
    return plan


@dataclass
class Task:
    """One object's life: spawned on the belt, then placed, missed or dropped."""

    cell: int
    task_id: int
    slot: int
    spawn_us: int
    size_m: float
    mass_kg: float
    yaw_rad: float
    grasp_us: int | None = None
    grasp_attempts: int = 0
    end_us: int | None = None
    outcome: str | None = None  # placed | missed | dropped | unfinished
    reason: str = ""
    resting_since_us: int | None = None

    def row(self) -> dict[str, Any]:
        return {
            "work_cell": self.cell, "task_id": self.task_id, "spawn_us": self.spawn_us,
            "grasp_us": self.grasp_us, "grasp_attempts": self.grasp_attempts,
            "end_us": self.end_us, "outcome": self.outcome, "success": self.outcome == "placed",
            "reason": self.reason, "size_m": self.size_m, "mass_kg": self.mass_kg,
            "yaw_rad": self.yaw_rad,
        }


@dataclass
class CellState:
    index: int
    origin: np.ndarray
    qadr: np.ndarray  # qpos addresses of the arm's six joints
    vadr: np.ndarray
    act: np.ndarray  # actuator ids of the six servos
    tcp: int  # site id of the cup lip
    cup: int  # body id of the tool
    obj_body: list[int]
    obj_geom: list[int]
    obj_qadr: list[int]
    obj_vadr: list[int]
    eq: list[int]
    half: list[float]  # half edge of each pool part as last spawned
    free_slots: list[int] = field(default_factory=list)
    active: dict[int, Task] = field(default_factory=dict)  # slot -> task
    suction: bool = False
    gripped: int | None = None  # slot held by the cup
    tasks_spawned: int = 0
    skipped_spawns: int = 0
    # What observations read of the parts in play, until they change (``World._observed``):
    # (whether the cup holds a part, ((task id, qpos address, dof address, held), ...) by task id).
    view: tuple[bool, tuple[tuple[int, int, int, bool], ...]] | None = None


class CellView:
    """Which geoms a cell camera cannot show: the other cells' geoms, when every one of them and
    its shadow lies outside the camera's view. Rendering a frame without them gives the same
    pixels (the scene is drawn geom by geom; one that covers no pixel and shadows none changes
    none) for the cost of one cell instead of the hall (half the time at 32 cells).

    Checked at every frame from the geoms' current positions and bounding spheres, so an arm or a
    part that comes near a neighbour's view is drawn; a camera that does not look straight down,
    a light that is not directional and a reflective material make every frame draw the hall."""

    def __init__(self, model: mujoco.MjModel) -> None:
        self.model = model
        self.groups = model.geom_group.copy()
        cell_of = np.full(model.ngeom, -1)
        for gid in range(model.ngeom):
            for name in (mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_GEOM, gid),
                         mujoco.mj_id2name(model, mujoco.mjtObj.mjOBJ_BODY, int(model.geom_bodyid[gid]))):
                head = (name or "").split("_", 1)[0]
                if head[:1] == "c" and head[1:].isdigit():
                    cell_of[gid] = int(head[1:])
                    break
        self.cell_of = cell_of
        self.visible = self.groups < 3  # what the default scene option draws
        # How far sideways a shadow falls per metre of height: the steepest directional light's.
        shadowed = model.light_castshadow.astype(bool)
        directional = model.light_type == mujoco.mjtLightType.mjLIGHT_DIRECTIONAL
        self.usable = bool((directional | ~shadowed).all()) and not (model.mat_reflectance > 0).any()
        dirs = model.light_dir[shadowed & directional]
        self.shadow_slope = max((math.hypot(d[0], d[1]) / max(-d[2], 1e-6) for d in dirs), default=0.0)
        self._others: dict[int, np.ndarray] = {}

    def out_of_view(self, data: mujoco.MjData, cell: int, camera: str, aspect: float) -> np.ndarray | None:
        """Ids of the geoms camera ``camera`` of ``cell`` cannot show now, or None when some other
        cell's geom may be in view (then the whole hall is drawn)."""
        if not self.usable:
            return None
        cam = mujoco.mj_name2id(self.model, mujoco.mjtObj.mjOBJ_CAMERA, camera)
        look = -data.cam_xmat[cam].reshape(3, 3)[:, 2]
        if look[2] > -CAMERA_DOWN_COS:
            return None
        others = self._others.get(cell)
        if others is None:
            others = self._others[cell] = np.flatnonzero(
                (self.cell_of >= 0) & (self.cell_of != cell) & self.visible)
        pos = data.cam_xpos[cam]
        # The view reaches farthest where it meets the floor: around the point below the camera,
        # at most its corner half-angle plus its tilt from the vertical.
        corner = math.atan(math.tan(math.radians(self.model.cam_fovy[cam]) / 2) * math.hypot(1.0, aspect))
        tilt = math.acos(min(1.0, -float(look[2])))
        reach = pos[2] * math.tan(min(corner + tilt, math.radians(89.0)))
        p = data.geom_xpos[others]
        rb = self.model.geom_rbound[others]
        gap = np.hypot(p[:, 0] - pos[0], p[:, 1] - pos[1]) - rb \
            - np.maximum(p[:, 2] + rb, 0.0) * self.shadow_slope
        if (rb > 0).all() and (gap > reach).all():
            return others
        return None


class World:
    """All N cells of the hall in one MuJoCo model."""

    def __init__(self, scenario: Scenario) -> None:
        self.sc = scenario
        self.model = build_model(scenario)
        self.data = mujoco.MjData(self.model)
        self.dt_us = scenario.physics_timestep_us
        self.t_us = 0
        self.size = scenario.work_cell.object_size_m
        self.mass = scenario.work_cell.object_mass_kg
        self.pool = object_pool_size(scenario)
        self.tasks: list[Task] = []
        m = self.model

        def nid(kind: mujoco.mjtObj, name: str) -> int:
            i = mujoco.mj_name2id(m, kind, name)
            if i < 0:
                raise KeyError(f"hall model has no {kind.name} named {name!r}")
            return i

        J, B, G = mujoco.mjtObj.mjOBJ_JOINT, mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_GEOM
        self.cells: list[CellState] = []
        for i, (x, y) in enumerate(scenario.hall.work_cell_origins(scenario.loops)):
            joints = [nid(J, f"c{i}_{name}") for name in JOINTS]
            frees = [nid(J, f"c{i}_obj{k}_free") for k in range(self.pool)]
            self.cells.append(CellState(
                index=i, origin=np.array([x, y, 0.0]),
                qadr=np.array([m.jnt_qposadr[j] for j in joints]),
                vadr=np.array([m.jnt_dofadr[j] for j in joints]),
                act=np.array([nid(mujoco.mjtObj.mjOBJ_ACTUATOR, f"c{i}_{name}") for name in JOINTS]),
                tcp=nid(mujoco.mjtObj.mjOBJ_SITE, f"c{i}_{TCP_SITE}"),
                cup=nid(B, f"c{i}_{CUP_BODY}"),
                obj_body=[nid(B, f"c{i}_obj{k}") for k in range(self.pool)],
                obj_geom=[nid(G, f"c{i}_obj{k}_geom") for k in range(self.pool)],
                obj_qadr=[int(m.jnt_qposadr[j]) for j in frees],
                obj_vadr=[int(m.jnt_dofadr[j]) for j in frees],
                eq=[nid(mujoco.mjtObj.mjOBJ_EQUALITY, f"c{i}_grip{k}") for k in range(self.pool)],
                half=[self.size / 2] * self.pool,
                free_slots=list(range(self.pool)),
            ))
        for c in self.cells:
            self.data.qpos[c.qadr] = HOME_Q
            self.data.ctrl[c.act] = HOME_Q
            for slot in range(self.pool):
                self._may_sleep(c, slot, True)
        mujoco.mj_forward(m, self.data)
        self._renderer: Any = None
        self._view = CellView(m)
        self._loose: tuple[list[tuple[CellState, int]], np.ndarray, np.ndarray, np.ndarray, np.ndarray] | None = None
        self._on_belt: np.ndarray | None = None  # dof addresses of the parts the belt carries
        self._check_steps = max(1, CHECK_PERIOD_US // self.dt_us)
        self._steps = 0
        self._vacuum: list[CellState] = []
        # What observations (``joint_state``, ``objects``) read: None for the live state, or a
        # snapshot (qpos, qvel, each cell's view) of the state at a step's start, taken while
        # that step runs in another thread; the snapshots still to be observed, by time.
        self._seen: Snapshot | None = None
        self._held: dict[int, Snapshot] = {}

    # ---- stepping ---------------------------------------------------------------------------
    def advance_to(self, t_us: int) -> None:
        """Step until the next step would pass ``t_us``."""
        while self.t_us + self.dt_us <= t_us:
            self.before_step()
            mujoco.mj_step(self.model, self.data)
            self.after_step()

    def before_step(self) -> None:
        """What a step begins with, before ``mj_step``: the conveyor drive. (A step may run its
        ``mj_step`` elsewhere, e.g. in a thread: ``before_step``, ``mj_step``, ``after_step``.)"""
        if self._on_belt is None or self._steps % self._check_steps == 0:
            self._on_belt = self._parts_on_belts()
        if self._on_belt.size:  # belt speed along x, nothing across
            self.data.qvel[self._on_belt] = self.sc.work_cell.belt_speed_m_s
            self.data.qvel[self._on_belt + 1] = 0.0

    def hold_observations(self) -> None:
        """Until ``release_observations``, observations show the state as it is now, while a step
        runs elsewhere (called before ``before_step``, whose belt drive sets velocities); it is
        kept for ``observe_at`` any time in this step, also once later steps have run."""
        snap = (self.data.qpos.copy(), self.data.qvel.copy(), [self._observed(c) for c in self.cells])
        self._held[self.t_us] = self._seen = snap

    def hold_ahead(self, steps: int) -> tuple[np.ndarray, np.ndarray]:
        """For ``steps`` steps handed over at once (``steps_alone``), after ``hold_observations``
        and ``before_step``: the rows (steps - 1, nq) and (steps - 1, nv) into which the stepping
        thread copies qpos and qvel at the start of each step after the first (before its belt
        drive), held for the observers of those steps. The parts in play do not change within."""
        qpos = np.empty((steps - 1, self.model.nq))
        qvel = np.empty((steps - 1, self.model.nv))
        views = self._held[self.t_us][2]
        for k in range(1, steps):
            self._held[self.t_us + k * self.dt_us] = (qpos[k - 1], qvel[k - 1], views)
        return qpos, qvel

    def steps_alone(self) -> int:
        """How many steps from now may run with nothing in Python between them: one while a cup
        waits to seal on a part (checked after every step), else up to the next task check, which
        also picks the parts the belt drives (``belt_drive``)."""
        if self._vacuum:
            return 1
        return self._check_steps - self._steps % self._check_steps

    def belt_drive(self) -> tuple[np.ndarray, float]:
        """What ``before_step`` sets (after it has run): dof addresses of the parts on a belt
        (int64), whose velocity becomes the belt speed along x and 0 across, and that speed."""
        on_belt = self._on_belt
        assert on_belt is not None, "belt_drive before before_step"
        return np.ascontiguousarray(on_belt, dtype=np.int64), float(self.sc.work_cell.belt_speed_m_s)

    def after_steps(self, steps: int) -> None:
        """What ``steps`` steps handed over at once end with: the clock, and the last step's
        seals and task checks (the ones before it had none: ``steps_alone``)."""
        self.t_us += (steps - 1) * self.dt_us
        self._steps += steps - 1
        self.after_step()

    def release_observations(self) -> None:
        """Observations show the live state again (the step that ran elsewhere has ended)."""
        self._seen = None

    def observe_at(self, t_us: int) -> None:
        """Observations show the state at ``t_us``: the held one of the step it falls in, or the
        live one if the world is at that step. Observations come in time order, so the snapshots
        of earlier steps are dropped."""
        start = t_us - t_us % self.dt_us
        held = self._held
        for k in [k for k in held if k < start]:
            del held[k]
        snap = held.get(start)
        if snap is None and start != self.t_us:
            raise RuntimeError(f"world: no state held for an observation at {t_us} us (the world is at {self.t_us} us)")
        self._seen = snap

    def _observed(self, c: CellState) -> tuple[bool, tuple[tuple[int, int, int, bool], ...]]:
        view = c.view
        if view is None:
            view = c.view = (c.gripped is not None, tuple(
                (task.task_id, c.obj_qadr[slot], c.obj_vadr[slot], c.gripped == slot)
                for slot, task in sorted(c.active.items(), key=lambda kv: kv[1].task_id)))
        return view

    def after_step(self) -> None:
        """What a step ends with, after ``mj_step``: the clock, suction seals and task outcomes."""
        self.t_us += self.dt_us
        self._steps += 1
        for c in self._vacuum:  # cups with the valve open and nothing held yet
            if c.active:
                self._try_seal(c)
        if self._steps % self._check_steps == 0:
            self._check_tasks()

    def _loose_parts(self) -> tuple[list[tuple[CellState, int]], np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """Parts in play and not held by a cup, as (rows, qpos addr (k,3), dof addr (k,),
        cell origins (k,3), half edges (k,)); rebuilt only when a part spawns, ends, is gripped
        or released, so that the per-step work is a few vectorised numpy operations."""
        if self._loose is None:
            rows = [(c, s) for c in self.cells for s in c.active if c.gripped != s]
            q = np.array([c.obj_qadr[s] for c, s in rows], dtype=np.int64)
            self._loose = (
                rows,
                q[:, None] + _OFFSETS if rows else np.zeros((0, 3), np.int64),
                np.array([c.obj_vadr[s] for c, s in rows], dtype=np.int64),
                np.array([c.origin for c, _ in rows]).reshape(-1, 3),
                np.array([c.half[s] for c, s in rows]),
            )
        return self._loose

    def _changed(self, c: CellState) -> None:
        """A part of ``c`` spawned, ended, was gripped or released: rebuild the per-step index and
        the cell's view."""
        self._loose = None
        self._on_belt = None
        c.view = None

    def _parts_on_belts(self) -> np.ndarray:
        """Dof addresses of the loose parts resting on their belt."""
        rows, qa, va, origin, half = self._loose_parts()
        if not rows:
            return va
        p = self.data.qpos[qa] - origin
        on = ((np.abs(p[:, 0]) <= g.BELT_HALF_LENGTH) & (np.abs(p[:, 1]) <= g.BELT_HALF_WIDTH)
              & (p[:, 2] <= g.BELT_TOP_Z + half + ON_BELT_SLACK_M))
        return va[on]

    def _check_tasks(self) -> None:
        rows, qa, va, origin, half = self._loose_parts()
        if not rows:
            return
        p = self.data.qpos[qa] - origin
        speed = np.linalg.norm(self.data.qvel[va[:, None] + _OFFSETS], axis=1)
        px, py = g.PLATFORM_CENTRE
        resting = ((np.abs(p[:, 0] - px) <= g.PLATFORM_HALF) & (np.abs(p[:, 1] - py) <= g.PLATFORM_HALF)
                   & (p[:, 2] <= g.PLATFORM_TOP_Z + half + 0.01) & (speed < SETTLE_SPEED_M_S))
        fallen = p[:, 2] < FALLEN_Z_M
        ended = []
        for k, (c, slot) in enumerate(rows):
            task = c.active[slot]
            if fallen[k]:
                ended.append((c, slot, "missed" if task.grasp_us is None else "dropped",
                               "fell off the belt end" if task.grasp_us is None else "released away from the platform"))
            elif resting[k]:
                if task.resting_since_us is None:
                    task.resting_since_us = self.t_us
                elif self.t_us - task.resting_since_us >= SETTLE_TIME_US:
                    ended.append((c, slot, "placed", "resting on the platform"))
            else:
                task.resting_since_us = None
        for c, slot, outcome, reason in ended:
            self._end(c, slot, outcome, reason)

    def _end(self, c: CellState, slot: int, outcome: str, reason: str) -> None:
        task = c.active.pop(slot)
        task.end_us, task.outcome, task.reason = self.t_us, outcome, reason
        metrics.TASKS.labels(outcome).inc()
        self._park(c, slot)
        c.free_slots.append(slot)
        self._changed(c)

    def _park(self, c: CellState, slot: int) -> None:
        m, d = self.model, self.data
        a, va = c.obj_qadr[slot], c.obj_vadr[slot]
        d.qpos[a:a + 3] = c.origin + np.array(park_position(slot))
        d.qpos[a + 3:a + 7] = [1, 0, 0, 0]
        d.qvel[va:va + 6] = 0.0
        self._collides(c, slot, 0, 0)
        m.body_gravcomp[c.obj_body[slot]] = 1.0
        self._may_sleep(c, slot, True)

    def _may_sleep(self, c: CellState, slot: int, parked: bool) -> None:
        """Let a parked part sleep, and a part in play never. MuJoCo skips a sleeping body's
        dynamics; a parked part has no contacts, its weight compensated and no velocity, so
        stepping it changes nothing and sleeping costs nothing (32 cells: 14% less per step).
        A part in play must not sleep: one at rest on the platform would freeze instead of keeping
        the contact solver's micrometre motions. The arms never sleep (actuated)."""
        tree = self.model.body_treeid[c.obj_body[slot]]
        self.model.tree_sleep_policy[tree] = SLEEP_ALLOWED if parked else SLEEP_NEVER

    def _collides(self, c: CellState, slot: int, contype: int, conaffinity: int) -> None:
        """Set a pool part's contact bits (the broad phase filters on the body's copy)."""
        m = self.model
        gid, bid = c.obj_geom[slot], c.obj_body[slot]
        m.geom_contype[gid] = m.body_contype[bid] = contype
        m.geom_conaffinity[gid] = m.body_conaffinity[bid] = conaffinity

    # ---- commands ---------------------------------------------------------------------------
    def spawn(self, cell: int, y_offset_m: float = 0.0, yaw_rad: float = 0.0,
              size_m: float | None = None, mass_kg: float | None = None) -> Task | None:
        """Put a part on the upstream end of the belt of ``cell`` (None if the pool is empty).
        ``size_m`` (edge) and ``mass_kg`` default to the scenario's nominal part."""
        c = self.cells[cell]
        if not c.free_slots:
            c.skipped_spawns += 1
            return None
        size = self.size if size_m is None else float(size_m)
        mass = self.mass if mass_kg is None else float(mass_kg)
        slot = c.free_slots.pop(0)
        self._shape(c, slot, size, mass)
        m, d = self.model, self.data
        a, va = c.obj_qadr[slot], c.obj_vadr[slot]
        d.qpos[a:a + 3] = c.origin + np.array([g.SPAWN_X, y_offset_m, g.BELT_TOP_Z + size / 2 + 0.001])
        d.qpos[a + 3:a + 7] = [np.cos(yaw_rad / 2), 0, 0, np.sin(yaw_rad / 2)]
        d.qvel[va:va + 6] = 0.0
        d.qvel[va] = self.sc.work_cell.belt_speed_m_s
        self._collides(c, slot, 1, 1)
        m.body_gravcomp[c.obj_body[slot]] = 0.0
        self._may_sleep(c, slot, False)  # the belt speed just set wakes it at the next step
        task = Task(cell=cell, task_id=c.tasks_spawned, slot=slot, spawn_us=self.t_us,
                    size_m=size, mass_kg=mass, yaw_rad=float(yaw_rad))
        c.tasks_spawned += 1
        c.active[slot] = task
        self.tasks.append(task)
        self._changed(c)
        return task

    def _shape(self, c: CellState, slot: int, size: float, mass: float) -> None:
        """Give pool part ``slot`` a cube of edge ``size`` and mass ``mass``: geometry, bounding
        volumes (the broad and mid phases use them), inertia and the mass-derived constants the
        compiler would have computed (subtree mass: the centre-of-mass frame of the dynamics;
        inverse weights: the constraint solver's scaling)."""
        h = size / 2
        if h == c.half[slot] and mass == self.model.body_mass[c.obj_body[slot]]:
            return
        m = self.model
        gid, bid = c.obj_geom[slot], c.obj_body[slot]
        m.geom_size[gid] = [h, h, h]
        m.geom_rbound[gid] = math.sqrt(3) * h
        m.geom_aabb[gid] = [0.0, 0.0, 0.0, h, h, h]
        if m.body_bvhnum[bid]:
            m.bvh_aabb[m.body_bvhadr[bid]] = [0.0, 0.0, 0.0, h, h, h]  # the body's one-geom tree
        inertia = mass * size**2 / 6  # solid cube about its centre
        m.body_subtreemass[0] += mass - m.body_mass[bid]
        m.body_mass[bid] = m.body_subtreemass[bid] = mass
        m.body_inertia[bid] = inertia
        m.body_invweight0[bid] = [1 / mass, 1 / inertia]
        va = c.obj_vadr[slot]
        m.dof_invweight0[va:va + 6] = [1 / mass] * 3 + [1 / inertia] * 3
        c.half[slot] = h

    def command(self, cell: int, q_target: list[float], suction: bool) -> None:
        """Set the six joint servo targets (rad) and the suction valve of ``cell``."""
        c = self.cells[cell]
        if len(q_target) != N_JOINTS:
            raise ValueError(f"cell {cell}: command has {len(q_target)} joint targets, the arm has "
                             f"{N_JOINTS} ({', '.join(JOINTS)})")
        lo = self.model.actuator_ctrlrange[c.act, 0]
        hi = self.model.actuator_ctrlrange[c.act, 1]
        self.data.ctrl[c.act] = np.clip(np.asarray(q_target, dtype=float), lo, hi)
        if suction and not c.suction:
            for task in c.active.values():  # each opening of the valve is one grasp attempt
                if task.grasp_us is None:
                    task.grasp_attempts += 1
                    break
        c.suction = suction
        if suction and c.gripped is None:
            self._try_seal(c)
        elif not suction and c.gripped is not None:
            self._release(c)
        self._vacuum = [x for x in self.cells if x.suction and x.gripped is None]

    def _try_seal(self, c: CellState) -> None:
        d = self.data
        tip = d.site_xpos[c.tcp]
        cup_axis = d.site_xmat[c.tcp].reshape(3, 3)[:, 2]
        if cup_axis[2] > -math.cos(SEAL_MAX_TILT):
            return  # the cup does not point down
        for slot, task in c.active.items():
            body = c.obj_body[slot]
            h = c.half[slot]
            rel = tip - d.xpos[body]
            if abs(rel[0]) > 2 * h or abs(rel[1]) > 2 * h or abs(rel[2]) > 2 * h + SEAL_DISTANCE_M:
                continue
            rot = d.xmat[body].reshape(3, 3)
            local = rot.T @ rel
            up = rot[2]  # world up in the part's frame
            k = int(np.argmax(np.abs(up)))
            if abs(up[k]) < math.cos(SEAL_MAX_TILT):
                continue  # no face looks up well enough for the cup
            above = local[k] * math.copysign(1.0, up[k]) - h
            lateral = np.delete(local, k)
            reach = h - CUP_RADIUS_M + SEAL_LIP_COMPLIANCE_M
            if -SEAL_PRESS_M <= above <= SEAL_DISTANCE_M and np.abs(lateral).max() <= reach:
                self._weld(c, slot)
                task.grasp_us = task.grasp_us or self.t_us
                return

    def _weld(self, c: CellState, slot: int) -> None:
        """Activate the grip weld, holding the part at its current pose relative to the cup."""
        m, d = self.model, self.data
        obj = c.obj_body[slot]
        eq = c.eq[slot]
        r1 = d.xmat[c.cup].reshape(3, 3)
        rel_pos = r1.T @ (d.xpos[obj] - d.xpos[c.cup])
        q1_inv = np.zeros(4)
        mujoco.mju_negQuat(q1_inv, d.xquat[c.cup])
        rel_quat = np.zeros(4)
        mujoco.mju_mulQuat(rel_quat, q1_inv, d.xquat[obj])
        m.eq_data[eq, 0:3] = 0.0
        m.eq_data[eq, 3:6] = rel_pos
        m.eq_data[eq, 6:10] = rel_quat
        m.eq_data[eq, 10] = 1.0
        d.eq_active[eq] = 1
        self._collides(c, slot, GRIPPED_CONTYPE, 1)
        c.gripped = slot
        self._vacuum = [x for x in self._vacuum if x is not c]
        self._changed(c)

    def _release(self, c: CellState) -> None:
        slot = c.gripped
        assert slot is not None
        self.data.eq_active[c.eq[slot]] = 0
        self._collides(c, slot, 1, 1)
        c.gripped = None
        self._changed(c)

    # ---- observation ------------------------------------------------------------------------
    def joint_state(self, cell: int) -> dict[str, Any]:
        c, seen = self.cells[cell], self._seen
        if seen is None:
            return {"q": [float(v) for v in self.data.qpos[c.qadr]], "gripped": c.gripped is not None}
        return {"q": [float(v) for v in seen[0][c.qadr]], "gripped": seen[2][cell][0]}

    def objects(self, cell: int) -> list[dict[str, Any]]:
        """Ground truth of the parts in play in ``cell`` (cell frame), by task id."""
        c, seen = self.cells[cell], self._seen
        qpos, qvel, view = (self.data.qpos, self.data.qvel, self._observed(c)) if seen is None else \
            (seen[0], seen[1], seen[2][cell])
        return [{"task_id": task_id, "p": [float(v) for v in qpos[a:a + 3] - c.origin],
                 "v": [float(v) for v in qvel[va:va + 3]], "gripped": held}
                for task_id, a, va, held in view[1]]

    def render(self, cell: int, width: int, height: int, camera: str = "camera",
               depth: bool = True) -> tuple[np.ndarray, np.ndarray | None]:
        """RGB (uint8 HxWx3) and depth (float32 metres along the optical axis) from a cell camera."""
        if self._renderer is None or self._renderer.width != width or self._renderer.height != height:
            if self._renderer is not None:
                self._renderer.close()
            self._renderer = mujoco.Renderer(self.model, height, width)
        r = self._renderer
        name = f"c{cell}_{camera}"
        hidden = self._view.out_of_view(self.data, cell, name, width / height)
        if hidden is not None:
            self.model.geom_group[hidden] = HIDDEN_GROUP
        try:
            r.disable_depth_rendering()
            r.update_scene(self.data, camera=name)
            rgb = r.render().copy()
            dep = None
            if depth:
                r.enable_depth_rendering()
                r.update_scene(self.data, camera=name)
                dep = r.render().copy()
                r.disable_depth_rendering()
        finally:
            if hidden is not None:
                self.model.geom_group[hidden] = self._view.groups[hidden]
        return rgb, dep

    def take_ended(self, upto_us: int) -> list[dict[str, Any]]:
        """Rows of the tasks that ended by ``upto_us`` since the last call, which ``tasks`` then
        forgets: a long run keeps only the tasks in play (``finish`` gives the rest). The bound
        keeps the rows' order independent of how far a step ahead had got."""
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
        if self._renderer is not None:
            self._renderer.close()
            self._renderer = None
