"""Constant-velocity Kalman tracking of the parts in one cell, stamped with capture time: each
track takes the nearest detection within a gate of its prediction, the detections left start
tracks, and tracks unseen for too long end (docs/perception.md, "Tracking")."""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from wire.bodies import Track

GATE_M = 0.08  # association gate around a predicted position
MAX_SILENCE_US = 1_500_000  # a track with no detection this long is dropped
ACCEL_SD = 0.5  # m/s^2, process noise: parts are carried at constant speed, then picked
MEAS_SD_M = 0.004  # position measurement noise of the estimator


@dataclass
class KalmanTrack:
    """One part's position and velocity (cell frame, m and m/s) and their covariance at the
    capture time ``t_us`` (us) of its last update; the robot predicts forward from there."""

    track_id: int
    t_us: int
    x: np.ndarray  # [px, py, pz, vx, vy, vz]
    P: np.ndarray
    updates: int = 1

    def predicted(self, t_us: int) -> np.ndarray:
        """The predicted position (m, cell frame) at ``t_us`` (us)."""
        return self.x[:3] + self.x[3:] * ((t_us - self.t_us) / 1e6)

    @property
    def position_sd_m(self) -> float:
        """The position's standard deviation (m, root mean of the three axes' variances)."""
        return float(np.sqrt(np.trace(self.P[:3, :3]) / 3))


class Tracker:
    """Tracks of one cell; a new track starts at ``initial_velocity`` (m/s, cell frame)."""

    def __init__(self, initial_velocity: tuple[float, float, float] = (0.0, 0.0, 0.0)) -> None:
        self.tracks: dict[int, KalmanTrack] = {}
        self._next_id = 0
        self.v0 = np.asarray(initial_velocity, float)
        self.last_update_us: int | None = None

    def update(self, t_us: int, positions: list[np.ndarray]) -> None:
        """Fold in the part positions ``positions`` (m, cell frame) seen in a frame captured at
        ``t_us`` (us) (frames in capture order)."""
        self.last_update_us = t_us
        unmatched = list(range(len(positions)))
        for tr in sorted(self.tracks.values(), key=lambda t: t.track_id):
            if not unmatched:
                break
            pred = tr.predicted(t_us)
            dists = [np.linalg.norm(positions[j] - pred) for j in unmatched]
            k = int(np.argmin(dists))
            if dists[k] <= GATE_M and t_us >= tr.t_us:
                self._correct(tr, t_us, positions[unmatched.pop(k)])
        for j in unmatched:
            P = np.diag([MEAS_SD_M**2] * 3 + [0.1**2] * 3)
            x = np.concatenate([positions[j], self.v0])
            self.tracks[self._next_id] = KalmanTrack(self._next_id, t_us, x, P)
            self._next_id += 1
        for tid in [tid for tid, tr in self.tracks.items() if t_us - tr.t_us > MAX_SILENCE_US]:
            del self.tracks[tid]

    @staticmethod
    def _correct(tr: KalmanTrack, t_us: int, z: np.ndarray) -> None:
        dt = (t_us - tr.t_us) / 1e6
        F = np.eye(6)
        F[:3, 3:] = np.eye(3) * dt
        q = ACCEL_SD**2
        Q = np.zeros((6, 6))
        Q[:3, :3] = np.eye(3) * q * dt**4 / 4
        Q[:3, 3:] = Q[3:, :3] = np.eye(3) * q * dt**3 / 2
        Q[3:, 3:] = np.eye(3) * q * dt**2
        x = F @ tr.x
        P = F @ tr.P @ F.T + Q
        H = np.hstack([np.eye(3), np.zeros((3, 3))])
        S = H @ P @ H.T + np.eye(3) * MEAS_SD_M**2
        K = P @ H.T @ np.linalg.inv(S)
        tr.x = x + K @ (z - H @ x)
        tr.P = (np.eye(6) - K @ H) @ P
        tr.t_us = t_us
        tr.updates += 1

    def report(self, belt_half_width_m: float) -> list[Track]:
        """Tracks over the belt (within ``belt_half_width_m``, m, of its axis, plus a margin) as
        plain data for a pose packet."""
        out: list[Track] = []
        for tr in sorted(self.tracks.values(), key=lambda t: t.track_id):
            if abs(tr.x[1]) > belt_half_width_m + 0.05:
                continue  # on the platform or in the gripper away from the belt
            out.append({"id": tr.track_id, "t_us": tr.t_us, "p": [round(float(v), 5) for v in tr.x[:3]],
                        "v": [round(float(v), 5) for v in tr.x[3:]], "sd": round(tr.position_sd_m, 5)})
        return out
