"""Forward and inverse kinematics of one cell's arm, on the robot node's own MjModel of the arm
placed at the cell's calibrated base pose: damped-least-squares IK of the 6-D tool pose,
warm-started, for one arm or many in lockstep (docs/physics.md, "Kinematics")."""

from __future__ import annotations

import math

import mujoco
import numpy as np

from domain import work_cell as g
from domain.arm import TCP_SITE, arm_model

DAMPING = 0.01  # DLS damping (m or rad): small against the singular values the cell allows (>= 0.065)
MAX_ITER_STEP_RAD = 0.2  # cap on one iteration's joint step, keeps far solves on one branch


def norm(v: np.ndarray) -> float:
    """Euclidean norm of the vector ``v``, computed as ``numpy.linalg.norm`` does (the square root
    of the dot product, so the same number to the last bit) without its dispatch, which costs
    more than the arithmetic on the 3- and 6-vectors a control period takes dozens of."""
    return math.sqrt(float(v.dot(v)))


def yaw_matrix(yaw: float) -> np.ndarray:
    """The rotation (3x3) by ``yaw`` (rad) about z."""
    c, s = math.cos(yaw), math.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


class ArmKinematics:
    """FK / IK of the arm in the cell frame, its base at ``base_pos`` (m, cell frame) turned
    ``base_yaw`` (rad) about z."""

    def __init__(self, base_pos: tuple[float, float, float] = g.ARM_BASE_POS,
                 base_yaw: float = g.ARM_BASE_YAW) -> None:
        self.model = arm_model()
        self.data = mujoco.MjData(self.model)
        self.site = self.model.site(TCP_SITE).id
        self.nq = self.model.nq
        self.base_p = np.asarray(base_pos, dtype=float)
        self.base_r = yaw_matrix(base_yaw)
        self.lo = self.model.jnt_range[:, 0].copy()
        self.hi = self.model.jnt_range[:, 1].copy()
        self._eye = np.eye(6) * DAMPING**2

    def _kin(self, q: np.ndarray) -> None:
        self.data.qpos[:] = q
        mujoco.mj_kinematics(self.model, self.data)

    def fk(self, q: np.ndarray | list[float]) -> tuple[np.ndarray, np.ndarray]:
        """Tool centre point position (m) and orientation (3x3) in the cell frame at joint
        positions ``q`` (rad)."""
        p = self.tcp_position(q)
        r = self.base_r @ self.data.site_xmat[self.site].reshape(3, 3)
        return p, r

    def tcp_position(self, q: np.ndarray | list[float]) -> np.ndarray:
        """Tool centre point position (m) in the cell frame at joint positions ``q`` (rad)
        (``fk`` without the orientation)."""
        self._kin(np.asarray(q, dtype=float))
        return self.base_r @ self.data.site_xpos[self.site] + self.base_p

    def tcp_positions(self, qs: np.ndarray) -> np.ndarray:
        """``tcp_position`` of each row of ``qs`` (n x nq, rad): n x 3 (m), the same to the bit,
        with one matrix product for all."""
        x = np.empty((len(qs), 3))
        for i, q in enumerate(qs):
            self._kin(q)
            x[i] = self.data.site_xpos[self.site]
        # A stack of matrix-vector products: the bits of ``base_r @ v`` for each row.
        return (self.base_r @ x[:, :, None])[:, :, 0] + self.base_p

    def jacobian(self, q: np.ndarray) -> np.ndarray:
        """6 x nq geometric Jacobian of the tool centre point (base frame) at joint positions
        ``q`` (rad)."""
        self._kin(q)
        return self._jac(self.data.site_xpos[self.site])

    def _jac(self, tcp: np.ndarray) -> np.ndarray:
        a = self.data.xaxis
        r = tcp - self.data.xanchor
        j = np.empty((6, self.nq))
        # rows 0-2: axis x (tcp - anchor), written out (np.cross costs more than the rest)
        j[0] = a[:, 1] * r[:, 2] - a[:, 2] * r[:, 1]
        j[1] = a[:, 2] * r[:, 0] - a[:, 0] * r[:, 2]
        j[2] = a[:, 0] * r[:, 1] - a[:, 1] * r[:, 0]
        j[3:] = a.T
        return j

    def solve(self, p: np.ndarray, rot: np.ndarray, q_seed: np.ndarray, iters: int = 4,
              tol: float = 1e-5) -> tuple[np.ndarray, float]:
        """Joint positions (rad) putting the tool at ``p`` (m) with orientation ``rot`` (3x3),
        cell frame, from ``q_seed`` (rad) in at most ``iters`` iterations, fewer once the pose
        error norm (m and rad) is under ``tol``; returns (q, remaining error norm). Best effort
        when the pose is unreachable."""
        pb = self.base_r.T @ (np.asarray(p, float) - self.base_p)
        rb = self.base_r.T @ np.asarray(rot, float)
        q = np.array(q_seed, dtype=float)
        err = math.inf
        for it in range(iters + 1):
            self._kin(q)
            x = self.data.site_xpos[self.site]
            m = rb @ self.data.site_xmat[self.site].reshape(3, 3).T
            e = np.empty(6)
            e[:3] = pb - x
            # Orientation error: sin(angle) * axis of the rotation from current to desired.
            e[3] = 0.5 * (m[2, 1] - m[1, 2])
            e[4] = 0.5 * (m[0, 2] - m[2, 0])
            e[5] = 0.5 * (m[1, 0] - m[0, 1])
            err = norm(e)
            if err < tol or it == iters:
                break
            j = self._jac(x)
            dq = j.T @ np.linalg.solve(j @ j.T + self._eye, e)
            big = max(map(abs, dq.tolist()))
            if big > MAX_ITER_STEP_RAD:
                dq *= MAX_ITER_STEP_RAD / big
            # np.clip's result (both are elementwise max then min) without its dispatch
            q = np.minimum(np.maximum(q + dq, self.lo), self.hi)
        return q, err

    def solve_many(self, p: np.ndarray, rot: np.ndarray, q_seed: np.ndarray, iters: int = 4,
                   tol: float = 1e-5) -> tuple[np.ndarray, np.ndarray]:
        """``solve`` for n arms with this model and base pose: tool positions ``p`` (n x 3, m),
        one orientation ``rot`` for all, seeds ``q_seed`` (n x nq, rad), ``iters`` and ``tol``
        as for ``solve``; returns (q, error norms) as
        ``solve`` returns them arm by arm, to the bit. An arm stops iterating when ``solve``
        would; the others go on."""
        n = len(q_seed)
        # Stacked matrix-vector products: (p - base) @ base_r is the same value, not the same bits.
        pb = (self.base_r.T @ (np.asarray(p, float) - self.base_p)[:, :, None])[:, :, 0]
        rb = self.base_r.T @ np.asarray(rot, float)
        q = np.array(q_seed, dtype=float)
        err = np.full(n, math.inf)
        active = np.arange(n)  # arms still iterating
        x, xmat = np.empty((n, 3)), np.empty((n, 3, 3))
        axis, anchor = np.empty((n, self.nq, 3)), np.empty((n, self.nq, 3))
        data = self.data
        for it in range(iters + 1):
            for i in active.tolist():
                self._kin(q[i])
                x[i] = data.site_xpos[self.site]
                xmat[i] = data.site_xmat[self.site].reshape(3, 3)
                axis[i] = data.xaxis
                anchor[i] = data.xanchor
            xa = x[active]
            m = rb @ xmat[active].transpose(0, 2, 1)
            e = np.empty((len(active), 6))
            e[:, :3] = pb[active] - xa
            e[:, 3] = 0.5 * (m[:, 2, 1] - m[:, 1, 2])
            e[:, 4] = 0.5 * (m[:, 0, 2] - m[:, 2, 0])
            e[:, 5] = 0.5 * (m[:, 1, 0] - m[:, 0, 1])
            ea = np.sqrt((e[:, None, :] @ e[:, :, None])[:, 0, 0])
            err[active] = ea
            go = ea >= tol
            if it == iters or not go.any():
                break
            active, e, xa = active[go], e[go], xa[go]
            j = self._jac_many(xa, axis[active], anchor[active])
            jt = j.transpose(0, 2, 1)
            dq = (jt @ np.linalg.solve(j @ jt + self._eye, e[:, :, None]))[:, :, 0]
            big = np.abs(dq).max(axis=1)
            over = big > MAX_ITER_STEP_RAD
            dq[over] *= (MAX_ITER_STEP_RAD / big[over])[:, None]
            q[active] = np.minimum(np.maximum(q[active] + dq, self.lo), self.hi)
        return q, err

    def _jac_many(self, tcp: np.ndarray, axis: np.ndarray, anchor: np.ndarray) -> np.ndarray:
        """``_jac`` of n arms: tcp (n x 3), hinge axes and anchors (n x nq x 3)."""
        r = tcp[:, None, :] - anchor
        j = np.empty((len(tcp), 6, self.nq))
        j[:, 0] = axis[:, :, 1] * r[:, :, 2] - axis[:, :, 2] * r[:, :, 1]
        j[:, 1] = axis[:, :, 2] * r[:, :, 0] - axis[:, :, 0] * r[:, :, 2]
        j[:, 2] = axis[:, :, 0] * r[:, :, 1] - axis[:, :, 1] * r[:, :, 0]
        j[:, 3:] = axis.transpose(0, 2, 1)
        return j
