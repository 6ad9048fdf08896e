"""The states observations read while steps run in another thread: each step's starting state,
held until the observers of that step have run (the protocol: docs/physics.md)."""

from __future__ import annotations

import numpy as np

from domain.cell_state import CellState

# What observations read of one cell: whether the cup holds a part, and per part in play by task
# id (task id, qpos address, dof address, held).
CellObservation = tuple[bool, tuple[tuple[int, int, int, bool], ...]]
# What observations read of one step: qpos, qvel, each cell's ``CellObservation``.
Snapshot = tuple[np.ndarray, np.ndarray, list[CellObservation]]


def observed(c: CellState) -> CellObservation:
    """What observations read of cell ``c``'s parts now (cached in ``c.view`` until they change)."""
    view = c.view
    if view is None:
        view = c.view = (c.gripped is not None, tuple(
            (task.task_id, c.obj_qadr[slot], c.obj_vadr[slot], c.gripped == slot)
            for slot, task in sorted(c.active.items(), key=lambda kv: kv[1].task_id)))
    return view


class HeldStates:
    """The snapshot observations show (``seen``: None for the live state) and the snapshots
    still to be observed, by the time (us) of the step they start; steps of ``dt_us`` (us)."""

    def __init__(self, dt_us: int) -> None:
        self.dt_us = dt_us
        self.seen: Snapshot | None = None
        self.held: dict[int, Snapshot] = {}

    def hold(self, t_us: int, snap: Snapshot) -> None:
        """Show ``snap``, the state at ``t_us`` (us), and keep it for observations in that step."""
        self.held[t_us] = self.seen = snap

    def hold_ahead(self, t_us: int, steps: int, nq: int, nv: int) -> tuple[np.ndarray, np.ndarray]:
        """Rows (steps - 1, ``nq``) and (steps - 1, ``nv``) for the starting qpos and qvel of
        the ``steps`` - 1 steps after the one held at ``t_us`` (us), held for their observers
        with that step's cell observations (the parts in play do not change within)."""
        qpos = np.empty((steps - 1, nq))
        qvel = np.empty((steps - 1, nv))
        views = self.held[t_us][2]
        for k in range(1, steps):
            self.held[t_us + k * self.dt_us] = (qpos[k - 1], qvel[k - 1], views)
        return qpos, qvel

    def observe_at(self, t_us: int, now_us: int) -> None:
        """Show the state at ``t_us`` (us): the held one of the step it falls in, or the live one
        if the world is at that step (``now_us``, us). Observations come in time order, so the
        snapshots of earlier steps are dropped."""
        start = t_us - t_us % self.dt_us
        held = self.held
        for k in [k for k in held if k < start]:
            del held[k]
        snap = held.get(start)
        if snap is None and start != now_us:
            raise RuntimeError(f"world: no state held for an observation at {t_us} us (the world is at {now_us} us)")
        self.seen = snap

    def release(self) -> None:
        """Show the live state again."""
        self.seen = None
