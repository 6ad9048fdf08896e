"""Each work cell's place in the hall's model (the ids and addresses of its arm, cup and pool
parts, looked up once) and its state: the parts in play, the valve and the part held."""

from __future__ import annotations

from dataclasses import dataclass, field

import mujoco
import numpy as np

from domain.arm import CUP_BODY, JOINTS, TCP_SITE
from domain.task_outcomes import Task
from scenario.schema import Scenario


@dataclass
class CellState:
    """One cell's ids and addresses in the hall's model (arm, cup, pool parts) and its state."""

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
    # What observations read of the parts in play, until they change (``snapshots.observed``):
    # (whether the cup holds a part, ((task id, qpos address, dof address, held), ...) by task id).
    view: tuple[bool, tuple[tuple[int, int, int, bool], ...]] | None = None


def index_cells(model: mujoco.MjModel, scenario: Scenario, pool: int, size_m: float) -> list[CellState]:
    """The cells of the hall ``model`` built for ``scenario``, each with ``pool`` part bodies of
    edge ``size_m`` (m), all free; KeyError naming a body, joint, site... the model lacks."""

    def nid(kind: mujoco.mjtObj, name: str) -> int:
        i = mujoco.mj_name2id(model, kind, name)
        if i < 0:
            raise KeyError(f"hall model has no {kind.name} named {name!r}")
        return i

    m = model
    J, B, G = mujoco.mjtObj.mjOBJ_JOINT, mujoco.mjtObj.mjOBJ_BODY, mujoco.mjtObj.mjOBJ_GEOM
    cells = []
    for i, (x, y) in enumerate(scenario.hall.work_cell_origins(scenario.loops)):
        joints = [nid(J, f"c{i}_{name}") for name in JOINTS]
        frees = [nid(J, f"c{i}_obj{k}_free") for k in range(pool)]
        cells.append(CellState(
            index=i, origin=np.array([x, y, 0.0]),
            qadr=np.array([m.jnt_qposadr[j] for j in joints]),
            vadr=np.array([m.jnt_dofadr[j] for j in joints]),
            act=np.array([nid(mujoco.mjtObj.mjOBJ_ACTUATOR, f"c{i}_{name}") for name in JOINTS]),
            tcp=nid(mujoco.mjtObj.mjOBJ_SITE, f"c{i}_{TCP_SITE}"),
            cup=nid(B, f"c{i}_{CUP_BODY}"),
            obj_body=[nid(B, f"c{i}_obj{k}") for k in range(pool)],
            obj_geom=[nid(G, f"c{i}_obj{k}_geom") for k in range(pool)],
            obj_qadr=[int(m.jnt_qposadr[j]) for j in frees],
            obj_vadr=[int(m.jnt_dofadr[j]) for j in frees],
            eq=[nid(mujoco.mjtObj.mjOBJ_EQUALITY, f"c{i}_grip{k}") for k in range(pool)],
            half=[size_m / 2] * pool,
            free_slots=list(range(pool)),
        ))
    return cells

