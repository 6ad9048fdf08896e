"""One part's task, from its spawn on the belt to its outcome (placed, missed, dropped or
unfinished), and the rule that decides the outcome from the loose parts' state."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any

import numpy as np

from domain import work_cell as g

SETTLE_SPEED_M_S = 0.02  # a part slower than this counts as resting
SETTLE_TIME_US = 200_000  # resting this long on the platform makes the task a success
FALLEN_Z_M = 0.5  # below this a part has left the belt/platform: task over
PLATFORM_SLACK_M = 0.01  # a part's centre this close above resting height is on the platform


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
        """The task as a ``tasks`` table row (times in us, sizes in m, mass in kg, yaw in rad)."""
        return {
            "work_cell": self.cell, "task_id": self.task_id, "spawn_us": self.spawn_us,
            "grasp_us": self.grasp_us, "grasp_attempts": self.grasp_attempts,
            "end_us": self.end_us, "outcome": self.outcome, "success": self.outcome == "placed",
            "reason": self.reason, "size_m": self.size_m, "mass_kg": self.mass_kg,
            "yaw_rad": self.yaw_rad,
        }


def judge(tasks: list[Task], p: np.ndarray, speed: np.ndarray, half: np.ndarray,
          t_us: int) -> list[tuple[int, str, str]]:
    """The tasks of loose parts that end at ``t_us`` (us), as (index into ``tasks``, outcome,
    reason); updates each task's resting time. ``p``: the parts' centres in their cell frame
    (k x 3, m); ``speed``: their linear speeds (k, m/s); ``half``: their half edges (k, m)."""
    px, py = g.PLATFORM_CENTRE
    resting = ((np.abs(p[:, 0] - px) <= g.PLATFORM_HALF) & (np.abs(p[:, 1] - py) <= g.PLATFORM_HALF)
               & (p[:, 2] <= g.PLATFORM_TOP_Z + half + PLATFORM_SLACK_M) & (speed < SETTLE_SPEED_M_S))
    fallen = p[:, 2] < FALLEN_Z_M
    ended = []
    for k, task in enumerate(tasks):
        if fallen[k]:
            ended.append((k, "missed" if task.grasp_us is None else "dropped",
                          "fell off the belt end" if task.grasp_us is None else "released away from the platform"))
        elif resting[k]:
            if task.resting_since_us is None:
                task.resting_since_us = t_us
            elif t_us - task.resting_since_us >= SETTLE_TIME_US:
                ended.append((k, "placed", "resting on the platform"))
        else:
            task.resting_since_us = None
    return ended
