"""The pick-and-place controller the robot node runs (and the abstract loops reuse).

It keeps time-stamped object estimates from the Edge, predicts the object to the moment the
command will act (delay-aware state correction: p + v * (t_act - t_capture)), tracks it with the
tool at belt speed while descending (conveyor tracking), seals the suction cup, lifts, places the
part on the platform and returns. Estimates older than ``max_estimate_age_ms`` make the arm
hold at a safe height instead of descending on a guess.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import StrEnum

import numpy as np

from services.common.scenario import RobotConfig
from services.physics import cell_geometry as g

HOVER_M = 0.08  # tool clearance above a part while tracking it
SAFE_Z_M = 1.0  # tool height for transfers
ALIGN_TOL_M = 0.008  # xy alignment needed before descending
SEAL_WAIT_US = 300_000  # no seal this long at the bottom: the grasp failed, retry
RELEASE_WAIT_US = 150_000  # valve-off to lift-off
MAX_SPEED_XY = 1.0  # m/s, tool speed limit of this arm class
MAX_SPEED_Z = 0.5  # m/s
HOME = np.array([-0.1, 0.0, SAFE_Z_M])


class Phase(StrEnum):
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
    """One arm's controller; ``step`` is called every control period."""

    def __init__(self, cfg: RobotConfig, object_size_m: float, servo_lag_s: float) -> None:
        self.cfg = cfg
        self.half = object_size_m / 2
        self.object_size = object_size_m
        # A command reaches the servo after the actuation latency; the servo then lags a moving
        # target by ~servo_lag_s: aim where the part will be by then.
        self.lead_us = cfg.actuation_latency_us + int(servo_lag_s * 1e6)
        self.phase = Phase.HOME
        self.tracks: dict[int, Track] = {}
        self.target: int | None = None
        self.q = g.joints_for_tool(HOME)
        self.gripped = False
        self.setpoint = HOME.copy()
        self.suction = False
        self.phase_since_us = 0
        self.picks = 0
        self.holds = 0  # control periods spent holding back on stale estimates

    # ---- inputs -----------------------------------------------------------------------------
    def on_estimate(self, tracks: list[dict]) -> None:
        """Replace the known tracks by the Edge's latest list (id, t_us, p, v)."""
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
        self.q = np.asarray(q, dtype=float)
        self.gripped = bool(gripped)

    # ---- control ----------------------------------------------------------------------------
    def predict(self, track: Track, t_us: int) -> np.ndarray:
        if not self.cfg.delay_compensation:
            return track.p.copy()
        return track.p + track.v * ((t_us - track.t_us) / 1e6)

    def _choose_target(self, now: int) -> Track | None:
        best = None
        for tr in self.tracks.values():
            if now - tr.t_us > self.cfg.max_estimate_age_ms * 1000:
                continue
            p = self.predict(tr, now + self.lead_us)
            if p[2] > g.BELT_TOP_Z + 3 * self.half or p[0] > g.PICK_X_RANGE[1] - 0.1:
                continue  # lifted already, or too far downstream to catch
            if best is None or p[0] > self.predict(best, now)[0]:
                best = tr
        return best

    def _set_phase(self, phase: Phase, now: int) -> None:
        self.phase = phase
        self.phase_since_us = now

    def step(self, now: int) -> tuple[np.ndarray, bool]:
        """Joint targets and suction command for the current control period."""
        tip = g.tool_position(self.q)
        goal = self.setpoint.copy()
        track = self.tracks.get(self.target) if self.target is not None else None
        stale = track is None or now - track.t_us > self.cfg.max_estimate_age_ms * 1000
        ph = self.phase

        if ph is Phase.HOME:
            goal = HOME.copy()
            self.suction = False
            cand = self._choose_target(now)
            if cand is not None:
                self.target = cand.track_id
                self._set_phase(Phase.APPROACH, now)
        elif ph in (Phase.APPROACH, Phase.DESCEND):
            if track is None:
                self.target = None
                self._set_phase(Phase.RETREAT, now)
            else:
                pred = self.predict(track, now + self.lead_us)
                top = pred[2] + self.half
                goal = np.array([pred[0], pred[1], top + HOVER_M])
                if pred[0] > g.PICK_X_RANGE[1]:
                    self.target = None
                    self.suction = False
                    self._set_phase(Phase.RETREAT, now)
                elif stale:
                    self.holds += 1
                    self.suction = False
                    if ph is Phase.DESCEND:
                        self._set_phase(Phase.APPROACH, now)
                elif ph is Phase.APPROACH:
                    aligned = np.linalg.norm(tip[:2] - pred[:2]) < ALIGN_TOL_M
                    if aligned and pred[0] >= g.PICK_X_RANGE[0]:
                        self._set_phase(Phase.DESCEND, now)
                else:
                    goal[2] = top - 0.002  # press lightly onto the part
                    self.suction = tip[2] - top < 0.02
                    if self.gripped:
                        self.picks += 1
                        self._set_phase(Phase.LIFT, now)
                    elif tip[2] - top < 0.004 and now - self.phase_since_us > SEAL_WAIT_US:
                        self.suction = False
                        self._set_phase(Phase.APPROACH, now)
        elif ph is Phase.LIFT:
            goal = np.array([self.setpoint[0], self.setpoint[1], SAFE_Z_M])
            if not self.gripped:
                self._set_phase(Phase.RETREAT, now)
            elif tip[2] > SAFE_Z_M - 0.05:
                self._set_phase(Phase.TRANSFER, now)
        elif ph is Phase.TRANSFER:
            px, py = g.PLATFORM_CENTRE
            goal = np.array([px, py, SAFE_Z_M])
            if not self.gripped:
                self._set_phase(Phase.RETREAT, now)
            elif np.linalg.norm(tip[:2] - goal[:2]) < 0.01:
                self._set_phase(Phase.LOWER, now)
        elif ph is Phase.LOWER:
            px, py = g.PLATFORM_CENTRE
            place_z = g.PLATFORM_TOP_Z + self.object_size + 0.004
            goal = np.array([px, py, place_z])
            if not self.gripped:
                self._set_phase(Phase.RETREAT, now)
            elif tip[2] - place_z < 0.006:
                self.suction = False
                self._set_phase(Phase.RELEASE, now)
        elif ph is Phase.RELEASE:
            self.suction = False
            if now - self.phase_since_us >= RELEASE_WAIT_US:
                self.target = None
                self._set_phase(Phase.RETREAT, now)
        elif ph is Phase.RETREAT:
            self.suction = self.gripped and self.suction
            goal = np.array([self.setpoint[0], self.setpoint[1], SAFE_Z_M])
            if tip[2] > SAFE_Z_M - 0.05:
                self._set_phase(Phase.HOME, now)

        self.setpoint = self._rate_limit(goal)
        return g.joints_for_tool(self.setpoint), self.suction

    def _rate_limit(self, goal: np.ndarray) -> np.ndarray:
        dt = self.cfg.control_period_us / 1e6
        step = goal - self.setpoint
        xy = step[:2]
        n = np.linalg.norm(xy)
        if n > MAX_SPEED_XY * dt:
            xy = xy * (MAX_SPEED_XY * dt / n)
        z = np.clip(step[2], -MAX_SPEED_Z * dt, MAX_SPEED_Z * dt)
        return self.setpoint + np.array([xy[0], xy[1], z])
