"""The vacuum cup: whether its lip seals on a part's upward face, and the weld that holds the
sealed part until the valve closes (the model and its limits: docs/physics.md)."""

from __future__ import annotations

import math

import mujoco
import numpy as np

from domain.arm import CUP_RADIUS_M
from domain.cell_state import CellState
from domain.part_pool import collides

SEAL_DISTANCE_M = 0.012  # bellows stroke: the lip seals from this high above the face ...
SEAL_PRESS_M = 0.004  # ... down to this far below it (bellows compressed)
SEAL_LIP_COMPLIANCE_M = 0.005  # the lip may overhang the face edge by this much and still seal
SEAL_MAX_TILT = math.radians(20)  # face normal and cup axis must agree within this
GRIPPED_CONTYPE = 4  # a held part stops colliding with the cup and arm (the weld holds it)


def seal_slot(data: mujoco.MjData, c: CellState) -> int | None:
    """The pool slot of the part in play in cell ``c`` on which the cup seals in the state
    ``data`` (positions in m), or None: the cup points down and its lip is on an upward face,
    within the bellows' stroke of it and not overhanging its edge."""
    tip = data.site_xpos[c.tcp]
    cup_axis = data.site_xmat[c.tcp].reshape(3, 3)[:, 2]
    if cup_axis[2] > -math.cos(SEAL_MAX_TILT):
        return None  # the cup does not point down
    for slot in c.active:
        body = c.obj_body[slot]
        h = c.half[slot]
        rel = tip - data.xpos[body]
        if abs(rel[0]) > 2 * h or abs(rel[1]) > 2 * h or abs(rel[2]) > 2 * h + SEAL_DISTANCE_M:
            continue
        rot = data.xmat[body].reshape(3, 3)
        local = rot.T @ rel
        up = rot[2]  # world up in the part's frame
        k = int(np.argmax(np.abs(up)))
        if abs(up[k]) < math.cos(SEAL_MAX_TILT):
            continue  # no face looks up well enough for the cup
        above = local[k] * math.copysign(1.0, up[k]) - h
        lateral = np.delete(local, k)
        reach = h - CUP_RADIUS_M + SEAL_LIP_COMPLIANCE_M
        if -SEAL_PRESS_M <= above <= SEAL_DISTANCE_M and np.abs(lateral).max() <= reach:
            return slot
    return None


def weld(model: mujoco.MjModel, data: mujoco.MjData, c: CellState, slot: int) -> None:
    """Hold pool part ``slot`` of cell ``c`` by activating its grip weld in the hall's ``model``
    and ``data`` at the part's current pose relative to the cup; the part stops colliding with
    the cup and the arm."""
    obj = c.obj_body[slot]
    eq = c.eq[slot]
    r1 = data.xmat[c.cup].reshape(3, 3)
    rel_pos = r1.T @ (data.xpos[obj] - data.xpos[c.cup])
    q1_inv = np.zeros(4)
    mujoco.mju_negQuat(q1_inv, data.xquat[c.cup])
    rel_quat = np.zeros(4)
    mujoco.mju_mulQuat(rel_quat, q1_inv, data.xquat[obj])
    model.eq_data[eq, 0:3] = 0.0
    model.eq_data[eq, 3:6] = rel_pos
    model.eq_data[eq, 6:10] = rel_quat
    model.eq_data[eq, 10] = 1.0
    data.eq_active[eq] = 1
    collides(model, c, slot, GRIPPED_CONTYPE, 1)
    c.gripped = slot


def release(model: mujoco.MjModel, data: mujoco.MjData, c: CellState) -> None:
    """Let go of the part the cup of cell ``c`` holds in the hall's ``model`` and ``data``: weld
    off, contacts back."""
    slot = c.gripped
    assert slot is not None
    data.eq_active[c.eq[slot]] = 0
    collides(model, c, slot, 1, 1)
    c.gripped = None
