"""The loose parts (in play, not held by a cup) as index arrays for vectorised per-step work, and
which of them ride their cell's kinematic belt."""

from __future__ import annotations

from typing import NamedTuple

import numpy as np

from domain import work_cell as g
from domain.cell_state import CellState
from domain.task_outcomes import Task

ON_BELT_SLACK_M = 0.004  # a part's centre this close above resting height rides the belt
OFFSETS = np.arange(3)  # x, y, z from a free joint's qpos (or dof) address


class LooseParts(NamedTuple):
    """Parts in play and not held by a cup, row by row."""

    rows: list[tuple[CellState, int]]  # (cell, pool slot)
    tasks: list[Task]
    qadr: np.ndarray  # qpos addresses of x, y, z (k x 3, int64)
    vadr: np.ndarray  # dof address of the linear velocity (k, int64)
    origin: np.ndarray  # cell origins (k x 3, m)
    half: np.ndarray  # half edges (k, m)


def loose_parts(cells: list[CellState]) -> LooseParts:
    """The loose parts of ``cells``, valid until a part spawns, ends, is gripped or released."""
    rows = [(c, s) for c in cells for s in c.active if c.gripped != s]
    q = np.array([c.obj_qadr[s] for c, s in rows], dtype=np.int64)
    return LooseParts(
        rows,
        [c.active[s] for c, s in rows],
        q[:, None] + OFFSETS if rows else np.zeros((0, 3), np.int64),
        np.array([c.obj_vadr[s] for c, s in rows], dtype=np.int64),
        np.array([c.origin for c, _ in rows]).reshape(-1, 3),
        np.array([c.half[s] for c, s in rows]),
    )


def on_belts(qpos: np.ndarray, loose: LooseParts) -> np.ndarray:
    """Dof addresses (int64) of the ``loose`` parts resting on their belt at positions ``qpos``."""
    if not loose.rows:
        return loose.vadr
    p = qpos[loose.qadr] - loose.origin
    on = ((np.abs(p[:, 0]) <= g.BELT_HALF_LENGTH) & (np.abs(p[:, 1]) <= g.BELT_HALF_WIDTH)
          & (p[:, 2] <= g.BELT_TOP_Z + loose.half + ON_BELT_SLACK_M))
    return loose.vadr[on]
