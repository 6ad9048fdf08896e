"""The parts of a cell's pool: when they arrive (``spawn_plan``), and how a pool body is put in
play on the belt with its size and mass, or parked below the floor asleep and without contacts."""

from __future__ import annotations

import math

import mujoco
import numpy as np

from domain import work_cell as g
from domain.cell_state import CellState
from domain.hall import park_position
from scenario.schema import Scenario

# Sleep policies of a kinematic tree (mjtSleepPolicy): see ``may_sleep``.
SLEEP_NEVER = int(mujoco.mjtSleepPolicy.mjSLEEP_NEVER)
SLEEP_ALLOWED = int(mujoco.mjtSleepPolicy.mjSLEEP_ALLOWED)


def spawn_plan(sc: Scenario, rng: np.random.Generator, step_us: int) -> list[tuple[int, dict[str, float]]]:
    """When and which parts one cell's belt receives over the run of ``sc``: (time us,
    ``World.spawn`` keyword arguments), on the physics step grid of ``step_us`` (us). The belt's
    phase (``first_object_spread_s``), spawn jitter, lateral offset, yaw, size and mass are drawn
    from ``rng`` (a spread of 0 draws nothing, so adding a spread to a scenario leaves the other
    draws of the stream unchanged)."""
    cfg = sc.work_cell

    def us(s: float) -> int:  # rounded, not truncated: 4.1 s is 4 099 999.9999999995 us in floats
        return int(round(s * 1e6))

    period = us(cfg.object_period_s)
    jitter = us(cfg.object_jitter_s)
    plan = []
    t = us(cfg.first_object_s)
    if cfg.first_object_spread_s:  # this belt's phase against the others'
        t += int(rng.integers(0, us(cfg.first_object_spread_s) + 1))
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


def place(model: mujoco.MjModel, data: mujoco.MjData, c: CellState, slot: int, y_offset_m: float,
          yaw_rad: float, size_m: float, mass_kg: float, belt_speed_m_s: float) -> None:
    """Put pool part ``slot`` of cell ``c`` in play in the hall's ``model`` and ``data``: a cube of
    edge ``size_m`` (m) and mass ``mass_kg`` (kg) on the upstream end of the belt, ``y_offset_m``
    (m) off its axis, turned ``yaw_rad`` (rad) about z and moving at ``belt_speed_m_s`` (m/s) with
    it."""
    shape(model, c, slot, size_m, mass_kg)
    a, va = c.obj_qadr[slot], c.obj_vadr[slot]
    data.qpos[a:a + 3] = c.origin + np.array([g.SPAWN_X, y_offset_m, g.BELT_TOP_Z + size_m / 2 + 0.001])
    data.qpos[a + 3:a + 7] = [np.cos(yaw_rad / 2), 0, 0, np.sin(yaw_rad / 2)]
    data.qvel[va:va + 6] = 0.0
    data.qvel[va] = belt_speed_m_s
    collides(model, c, slot, 1, 1)
    model.body_gravcomp[c.obj_body[slot]] = 0.0
    may_sleep(model, c, slot, False)  # the belt speed just set wakes it at the next step


def park(model: mujoco.MjModel, data: mujoco.MjData, c: CellState, slot: int) -> None:
    """Take pool part ``slot`` of cell ``c`` out of play in the hall's ``model`` and ``data``: at
    rest at its park position, without contacts, its weight compensated, allowed to sleep."""
    a, va = c.obj_qadr[slot], c.obj_vadr[slot]
    data.qpos[a:a + 3] = c.origin + np.array(park_position(slot))
    data.qpos[a + 3:a + 7] = [1, 0, 0, 0]
    data.qvel[va:va + 6] = 0.0
    collides(model, c, slot, 0, 0)
    model.body_gravcomp[c.obj_body[slot]] = 1.0
    may_sleep(model, c, slot, True)


def may_sleep(model: mujoco.MjModel, c: CellState, slot: int, parked: bool) -> None:
    """Let pool part ``slot`` of cell ``c`` sleep if ``parked``, else never (a policy of the hall's
    ``model``). MuJoCo skips a sleeping body's dynamics; a parked part has no contacts, its weight
    compensated and no velocity, so stepping it changes nothing and sleeping costs nothing (32
    cells: 14% less per step). A part in play must not sleep: one at rest on the platform would
    freeze instead of keeping the contact solver's micrometre motions. The arms never sleep
    (actuated)."""
    tree = model.body_treeid[c.obj_body[slot]]
    model.tree_sleep_policy[tree] = SLEEP_ALLOWED if parked else SLEEP_NEVER


def collides(model: mujoco.MjModel, c: CellState, slot: int, contype: int, conaffinity: int) -> None:
    """Set the contact bits ``contype`` and ``conaffinity`` of pool part ``slot`` of cell ``c`` in
    the hall's ``model`` (the broad phase filters on the body's copy)."""
    gid, bid = c.obj_geom[slot], c.obj_body[slot]
    model.geom_contype[gid] = model.body_contype[bid] = contype
    model.geom_conaffinity[gid] = model.body_conaffinity[bid] = conaffinity


def shape(model: mujoco.MjModel, c: CellState, slot: int, size_m: float, mass_kg: float) -> None:
    """Give pool part ``slot`` of cell ``c`` in the hall's ``model`` a cube of edge ``size_m`` (m)
    and mass ``mass_kg`` (kg): geometry, bounding volumes (the broad and mid phases use them),
    inertia and the mass-derived constants the compiler would have computed (subtree mass: the
    centre-of-mass frame of the dynamics; inverse weights: the constraint solver's scaling)."""
    h = size_m / 2
    if h == c.half[slot] and mass_kg == model.body_mass[c.obj_body[slot]]:
        return
    m = model
    gid, bid = c.obj_geom[slot], c.obj_body[slot]
    m.geom_size[gid] = [h, h, h]
    m.geom_rbound[gid] = math.sqrt(3) * h
    m.geom_aabb[gid] = [0.0, 0.0, 0.0, h, h, h]
    if m.body_bvhnum[bid]:
        m.bvh_aabb[m.body_bvhadr[bid]] = [0.0, 0.0, 0.0, h, h, h]  # the body's one-geom tree
    inertia = mass_kg * size_m**2 / 6  # solid cube about its centre
    m.body_subtreemass[0] += mass_kg - m.body_mass[bid]
    m.body_mass[bid] = m.body_subtreemass[bid] = mass_kg
    m.body_inertia[bid] = inertia
    m.body_invweight0[bid] = [1 / mass_kg, 1 / inertia]
    va = c.obj_vadr[slot]
    m.dof_invweight0[va:va + 6] = [1 / mass_kg] * 3 + [1 / inertia] * 3
    c.half[slot] = h
