"""The pick-and-place controller of one cell's 6-DOF arm, which the robot node runs and the
abstract loops reuse: delay-aware prediction of the Edge's estimates, intercept, conveyor
tracking, a limited Cartesian setpoint through IK (docs/physics.md, "The controller")."""

from __future__ import annotations

import math
from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from domain import work_cell as g
from domain.arm import HOME_Q, JOINT_SPEED_MAX_RAD_S, TCP_SPEED_MAX_M_S
from domain.kinematics import ArmKinematics, norm
from scenario.schema import RobotConfig
from wire import bodies

HOVER_M = 0.05  # cup clearance above a part's top while aligning over it
SEAL_CLEARANCE_M = 0.004  # descend the cup lip to this above the expected top (seal band: 12 mm)
SAFE_Z_M = 1.0  # cup height after a retreat
LIFT_M = 0.06  # lift a gripped part this far before carrying it sideways
PLACE_CLEARANCE_M = 0.006  # let go with the part's bottom this far above the platform
ALIGN_TOL_M = 0.010  # cup-over-part alignment needed before descending (seal tolerance: 20 mm)
SPEED_MATCH_M_S = 0.15  # cup must move with the part (within estimate noise) before descending
SERVO_TOL_M = 0.015  # measured cup must be this close to the plan before descending
COMMIT_M = 0.025  # below this height above the part a descent finishes even on a stale estimate
SEAL_WAIT_US = 300_000  # no seal this long at the bottom: the grasp failed, retry
RELEASE_WAIT_US = 150_000  # valve off to lift off
PLACE_WAIT_US = 150_000  # cup stopped short of the place height this long: the part is down
TRANSFER_TIMEOUT_US = 3_000_000  # carry that has not arrived by then lowers where it is
TCP_ACCEL_M_S2 = 4.0  # acceleration limit of the cup setpoint
DESCEND_SPEED_M_S = 0.25  # vertical approach speed onto a part and onto the platform
APPROACH_SPEED_M_S = 0.7  # average cup speed assumed when planning an intercept
GRASP_TIME_S = 0.5  # alignment to sealed grip, with margin: the part must stay in the window
GIVE_UP_US = 1_000_000  # no estimate of the target this long (or 2 x the hold age): give it up
CONVERGE_TAU_S = 0.08  # time constant of the final convergence onto a goal (estimate noise
# moves the goal by millimetres between frames; a shorter one makes the cup jitter with it)


class Phase(StrEnum):
    """The controller's phases, in the order of a pick and place."""

    HOME = "home"
    APPROACH = "approach"
    DESCEND = "descend"
    LIFT = "lift"
    TRANSFER = "transfer"
    LOWER = "lower"
    RELEASE = "release"
    RETREAT = "retreat"


@dataclass
class Track:
    """An object estimate: position and velocity (cell frame) at capture time ``t_us``."""

    track_id: int
    t_us: int
    p: np.ndarray
    v: np.ndarray


class PickController:
    """One arm's controller; ``step`` is called every control period.

    ``step`` is ``plan`` (the state machine and the cup setpoint), the IK of the setpoint, then
    ``command`` (joint targets from the IK solution). Whoever drives many arms calls the three
    itself, to solve the IK of all arms in one ``ArmKinematics.solve_many``. ``cfg``: the
    scenario's robot section; ``object_size_m``: the nominal part edge (m); ``servo_lag_s``: the
    servos' lag (s)."""

    def __init__(self, cfg: RobotConfig, object_size_m: float, servo_lag_s: float) -> None:
        self.cfg = cfg
        self.half = object_size_m / 2
        self.object_size = object_size_m
        self.hover = np.array([0.0, 0.0, self.half + HOVER_M])  # cup over a part's centre
        self.servo_lag_s = servo_lag_s
        self.dt = cfg.control_period_us / 1e6
        # A command reaches the drives after the actuation latency and holds for one period: the
        # plan is for the middle of that interval.
        self.lead_us = cfg.actuation_latency_us + cfg.control_period_us // 2
        self.max_age_us = int(cfg.max_estimate_age_ms * 1000)
        self.give_up_us = max(GIVE_UP_US, 2 * self.max_age_us)
        self.kin = ArmKinematics()
        self.rot = np.array(g.TOOL_DOWN, dtype=float)
        self.home = np.array(g.HOME_TOOL_POS, dtype=float)
        self.q = np.array(HOME_Q, dtype=float)  # measured joint positions
        self.q_sp = self.q.copy()  # planned joint positions
        self.p_sp = self.kin.tcp_position(self.q)  # planned cup position (cell frame)
        self.v_sp = np.zeros(3)
        self.synced = False
        self.gripped = False
        self.suction = False
        self.phase = Phase.HOME
        self.phase_since_us = 0
        self.tracks: dict[int, Track] = {}
        self.target: int | None = None
        self.target_track: Track | None = None  # last estimate of the target
        self.grasp_xyz = self.p_sp.copy()
        self.part_height = object_size_m
        self.bottom_since_us: int | None = None
        self.picks = 0
        self.holds = 0  # control periods spent holding back on stale estimates
        self.ik_error_m = 0.0  # worst IK residual seen (m or rad), for diagnostics

    # ---- inputs -----------------------------------------------------------------------------
    def on_estimate(self, tracks: list[bodies.Track]) -> None:
        """Replace the known tracks by the Edge's latest list ``tracks`` (id, capture time t_us in
        us, position p in m and velocity v in m/s in the cell frame)."""
        fresh = {}
        for tr in tracks:
            tid = int(tr["id"])
            old = self.tracks.get(tid)
            if old is not None and old.t_us > int(tr["t_us"]):
                fresh[tid] = old  # a reordered, older estimate never overrides a newer one
            else:
                fresh[tid] = Track(tid, int(tr["t_us"]), np.asarray(tr["p"], float), np.asarray(tr["v"], float))
        self.tracks = fresh

    def on_state(self, q: list[float], gripped: bool) -> None:
        """Measured joint positions ``q`` (rad, six) and whether the cup holds a part
        (``gripped``)."""
        self.q = np.asarray(q, dtype=float)
        self.gripped = bool(gripped)
        if not self.synced:  # start planning from where the arm really is
            self.synced = True
            self.q_sp = self.q.copy()
            self.p_sp = self.kin.tcp_position(self.q)
            self.v_sp[:] = 0.0

    # ---- prediction and target choice -----------------------------------------------------------
    def predict(self, track: Track, t_us: int) -> np.ndarray:
        """Where the part of ``track`` is at ``t_us`` (us; m, cell frame). Parts ride the belt:
        only their motion in the belt plane is extrapolated (a vertical velocity in an estimate
        is settling or noise)."""
        p = track.p.copy()
        if self.cfg.delay_compensation:
            p[:2] += track.v[:2] * ((t_us - track.t_us) / 1e6)
        return p

    def _lost_track(self, track: Track, pred: np.ndarray, now: int) -> bool:
        """Give the target up: no estimate for too long, or it left the belt or the window."""
        return (now - track.t_us > self.give_up_us or abs(pred[1]) > g.BELT_HALF_WIDTH
                or pred[0] > g.PICK_X_RANGE[1])

    def _fresh(self, track: Track | None, now: int) -> bool:
        return track is not None and now - track.t_us <= self.max_age_us

    def _choose_target(self, now: int) -> Track | None:
        """The fresh, catchable part that leaves the pick window first."""
        best, best_x = None, -math.inf
        for tr in self.tracks.values():
            if not self._fresh(tr, now):
                continue
            p = self.predict(tr, now + self.lead_us)
            if p[2] > g.BELT_TOP_Z + 3 * self.half or abs(p[1]) > g.BELT_HALF_WIDTH:
                continue  # lifted already, or not on the belt
            hover = p + self.hover
            t_grasp = norm(hover - self.p_sp) / APPROACH_SPEED_M_S + GRASP_TIME_S
            if max(p[0], g.PICK_X_RANGE[0]) + tr.v[0] * t_grasp > g.PICK_X_RANGE[1]:
                continue  # would leave the window before the grip
            if p[0] > best_x:
                best, best_x = tr, p[0]
        return best

    def _intercept(self, track: Track, now: int) -> tuple[np.ndarray, np.ndarray]:
        """Hover point over the part where the cup can meet it, and the velocity to match there.
        Upstream of the pick window the cup waits at the window's entry."""
        t = now + self.lead_us
        aim = self.predict(track, t)
        for _ in range(2):  # time to get there, at the planning speed, then where the part is
            hover = aim + self.hover
            eta_us = int(norm(hover - self.p_sp) / APPROACH_SPEED_M_S * 1e6)
            aim = self.predict(track, t + eta_us)
        goal = aim + self.hover
        vel = np.array([track.v[0], track.v[1], 0.0])
        if goal[0] < g.PICK_X_RANGE[0]:
            goal[0], vel[:] = g.PICK_X_RANGE[0], 0.0
        # Never chase an estimate off the pick window.
        goal[0] = min(goal[0], g.PICK_X_RANGE[1])
        goal[1] = min(max(goal[1], -g.BELT_HALF_WIDTH), g.BELT_HALF_WIDTH)
        return goal, vel

    # ---- the state machine ------------------------------------------------------------------------
    def _set_phase(self, phase: Phase, now: int) -> None:
        self.phase = phase
        self.phase_since_us = now
        self.bottom_since_us = None

    def step(self, now: int) -> tuple[np.ndarray, bool]:
        """Joint targets (rad, six) and suction command for the control period starting at
        ``now`` (us)."""
        self.plan(now)
        q, err = self.kin.solve(self.p_sp, self.rot, self.q_sp)
        return self.command(q, err), self.suction

    def plan(self, now: int, tip: np.ndarray | None = None) -> None:
        """Advance the state machine, the suction command and the cup setpoint ``p_sp`` (the pose
        the IK then solves for, from ``q_sp``, with orientation ``rot``) one control period, the
        one starting at ``now`` (us); ``tip``: the cup's position at the measured joints (m, cell
        frame; None: computed here)."""
        if tip is None:
            tip = self.kin.tcp_position(self.q)
        track = None
        if self.target is not None:
            # A target missing from the latest list (occluded by the cup, or just sealed and
            # not yet reported as held) keeps its last estimate, which then ages normally.
            track = self.tracks.get(self.target, self.target_track)
            self.target_track = track
        goal, vel, vmax = self.p_sp.copy(), np.zeros(3), TCP_SPEED_MAX_M_S
        ph = self.phase

        if ph is Phase.HOME:
            self.suction = False
            goal = self.home.copy()
            cand = self._choose_target(now)
            if cand is not None:
                self.target, self.target_track = cand.track_id, cand
                self._set_phase(Phase.APPROACH, now)
                goal, vel = self._intercept(cand, now)
        elif ph is Phase.APPROACH:
            self.suction = False
            if self.gripped:  # sealed just as a descent was called off: keep the part
                self.suction = True
                self._gripped(now, tip)
                goal, vel = self._lift_goal(), np.zeros(3)
            elif track is None:
                self.target = None
                self._set_phase(Phase.RETREAT, now)
            else:
                pred = self.predict(track, now + self.lead_us)
                goal, vel = self._intercept(track, now)
                if self._lost_track(track, pred, now):
                    self.target = None
                    self._set_phase(Phase.RETREAT, now)
                elif not self._fresh(track, now):
                    self.holds += 1  # hold over the part; never descend on a stale estimate
                elif (pred[0] >= g.PICK_X_RANGE[0]
                      and pred[0] + track.v[0] * GRASP_TIME_S <= g.PICK_X_RANGE[1]
                      and norm(self.p_sp[:2] - pred[:2]) < ALIGN_TOL_M
                      and norm(self.v_sp[:2] - track.v[:2]) < SPEED_MATCH_M_S
                      and norm(tip - self.p_sp) < SERVO_TOL_M):
                    self._set_phase(Phase.DESCEND, now)
                    self.suction = True  # vacuum on before contact, as on a real cell
        elif ph is Phase.DESCEND:
            if track is None:
                self.target = None
                self.suction = False
                self._set_phase(Phase.RETREAT, now)
            else:  # never None here: the target keeps its last estimate
                pred = self.predict(track, now + self.lead_us)
                top = pred[2] + self.half
                goal = np.array([pred[0], pred[1], top + SEAL_CLEARANCE_M])
                vel = np.array([track.v[0], track.v[1], 0.0])
                vmax = DESCEND_SPEED_M_S
                if self.gripped:
                    self._gripped(now, tip)
                    goal, vel = self._lift_goal(), np.zeros(3)
                elif not self._fresh(track, now) and self.p_sp[2] > top + COMMIT_M:
                    self.holds += 1  # stale before the commit height: back up and hold
                    self.suction = False
                    self._set_phase(Phase.APPROACH, now)
                elif self._lost_track(track, pred, now):
                    self.target = None
                    self.suction = False
                    self._set_phase(Phase.RETREAT, now)
                elif abs(self.p_sp[2] - goal[2]) < 0.002:
                    self.bottom_since_us = self.bottom_since_us or now
                    if now - self.bottom_since_us > SEAL_WAIT_US:
                        self.suction = False  # no seal: back up over the part and try again
                        self._set_phase(Phase.APPROACH, now)
        elif ph is Phase.LIFT:
            goal = self._lift_goal()
            if not self.gripped:
                self._lost(now)
            elif tip[2] > goal[2] - 0.02:
                self._set_phase(Phase.TRANSFER, now)
        elif ph is Phase.TRANSFER:
            place = self._place_point()
            goal = place + np.array([0.0, 0.0, 0.05])
            if not self.gripped:
                self._lost(now)
            elif ((norm(tip[:2] - place[:2]) < 0.01 and norm(self.p_sp - goal) < 0.005)
                  or now - self.phase_since_us > TRANSFER_TIMEOUT_US):
                self._set_phase(Phase.LOWER, now)
        elif ph is Phase.LOWER:
            goal = self._place_point()
            vmax = DESCEND_SPEED_M_S
            if not self.gripped:
                self._lost(now)
            elif norm(self.p_sp - goal) < 0.002:
                self.bottom_since_us = self.bottom_since_us or now
                # Let go once the cup is there, or once it has stopped short (the part already
                # touches the platform).
                if abs(tip[2] - goal[2]) < 0.004 or now - self.bottom_since_us > PLACE_WAIT_US:
                    self.suction = False
                    self._set_phase(Phase.RELEASE, now)
        elif ph is Phase.RELEASE:
            self.suction = False
            if now - self.phase_since_us >= RELEASE_WAIT_US:
                self.target = None
                self._set_phase(Phase.RETREAT, now)
        elif ph is Phase.RETREAT:
            self.suction = False
            goal = np.array([self.p_sp[0], self.p_sp[1], SAFE_Z_M])
            if tip[2] > SAFE_Z_M - 0.1:
                self._set_phase(Phase.HOME, now)

        self._move(goal, vel, vmax)

    def _gripped(self, now: int, tip: np.ndarray) -> None:
        """The cup holds the part: remember where, and how far below the lip the part's bottom
        hangs (it was resting on the belt when the cup sealed: measured from the joints, not
        from the vision estimate), then lift."""
        self.picks += 1
        self.grasp_xyz = self.p_sp.copy()
        self.part_height = float(np.clip(tip[2] - g.BELT_TOP_Z, 0.01, 0.3))
        self._set_phase(Phase.LIFT, now)

    def _lift_goal(self) -> np.ndarray:
        return self.grasp_xyz + np.array([0.0, 0.0, LIFT_M])

    def _place_point(self) -> np.ndarray:
        px, py = g.PLATFORM_CENTRE
        return np.array([px, py, g.PLATFORM_TOP_Z + self.part_height + PLACE_CLEARANCE_M])

    def _lost(self, now: int) -> None:
        """The part left the cup before the platform."""
        self.target = None
        self.suction = False
        self._set_phase(Phase.RETREAT, now)

    # ---- motion -------------------------------------------------------------------------------
    def _move(self, goal: np.ndarray, vel: np.ndarray, vmax: float) -> None:
        """Advance the cup setpoint one period towards ``goal`` moving at ``vel``: velocity
        feed-forward plus a correction limited by speed, braking distance and a final time
        constant; total speed and acceleration limited."""
        dt = self.dt
        err = goal - self.p_sp
        dist = norm(err)
        v_des = vel.copy()
        if dist > 1e-9:
            corr = min(vmax, math.sqrt(2 * TCP_ACCEL_M_S2 * dist), dist / CONVERGE_TAU_S)
            v_des += err * (corr / dist)
        speed = norm(v_des)
        if speed > TCP_SPEED_MAX_M_S:
            v_des *= TCP_SPEED_MAX_M_S / speed
        dv = v_des - self.v_sp
        n = norm(dv)
        if n > TCP_ACCEL_M_S2 * dt:
            dv *= TCP_ACCEL_M_S2 * dt / n
        self.v_sp += dv
        self.p_sp += self.v_sp * dt

    def command(self, q: np.ndarray, err: float) -> np.ndarray:
        """Joint targets (rad) from the setpoint's IK solution ``q`` (rad; residual ``err``, m or
        rad): joint speed limit, servo-lag feed-forward."""
        self.ik_error_m = max(self.ik_error_m, err)
        dq = q - self.q_sp
        limit = JOINT_SPEED_MAX_RAD_S * self.dt
        over = max(map(abs, dq.tolist())) / limit
        if over > 1.0:  # slow the whole move down so no joint exceeds its speed
            q = self.q_sp + dq / over
            self.p_sp = self.kin.tcp_position(q)
            self.v_sp /= over
        qd = (q - self.q_sp) / self.dt
        self.q_sp = q
        return q + qd * self.servo_lag_s
