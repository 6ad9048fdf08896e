"""Geometry of one conveyor cell, in the cell frame (origin on the floor at the cell centre, x along
the belt, z up). Shared by the scene builder, the robot controller and the Edge so that every
node agrees on where the belt, the platform and the camera are (as a calibrated real cell would).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

BELT_TOP_Z = 0.75  # m, belt surface height: a common working height
BELT_HALF_LENGTH = 0.6  # m, belt runs x in [-0.6, 0.6]
BELT_HALF_WIDTH = 0.2  # m
SPAWN_X = -0.55  # m, objects appear at the upstream end
PLATFORM_CENTRE = (0.0, 0.55)  # m, drop-off platform beside the belt
PLATFORM_HALF = 0.15  # m, platform is 0.3 x 0.3 m
PLATFORM_TOP_Z = 0.75  # m
GANTRY_Z = 1.30  # m, height of the gantry's z-axis origin
CUP_LENGTH = 0.02  # m, suction cup below the z carriage
PICK_X_RANGE = (-0.40, 0.45)  # m, stretch of belt where the arm may grasp
JOINT_RANGES = {"x": (-0.55, 0.55), "y": (-0.25, 0.75), "z": (-0.50, 0.0)}  # m
CAMERA_HEIGHT_ABOVE_BELT = 1.0  # m, camera looks straight down at the belt centre
CAMERA_X = 0.0  # m


def tool_position(q: np.ndarray | list[float]) -> np.ndarray:
    """Suction-cup tip position (cell frame) for gantry joint positions q = (x, y, z)."""
    return np.array([q[0], q[1], GANTRY_Z + q[2] - CUP_LENGTH])


def joints_for_tool(p: np.ndarray | list[float]) -> np.ndarray:
    """Inverse kinematics of the Cartesian gantry: joint positions placing the tip at p, clipped
    to the joint ranges."""
    q = np.array([p[0], p[1], p[2] - GANTRY_Z + CUP_LENGTH], dtype=float)
    for i, axis in enumerate("xyz"):
        lo, hi = JOINT_RANGES[axis]
        q[i] = min(max(q[i], lo), hi)
    return q


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics of a downward camera; pixel (u, v) with v growing downwards."""

    width: int
    height: int
    fovy_deg: float

    @property
    def f_px(self) -> float:
        return (self.height / 2) / np.tan(np.radians(self.fovy_deg) / 2)

    @property
    def centre(self) -> tuple[float, float]:
        return ((self.width - 1) / 2, (self.height - 1) / 2)

    def back_project(self, u: float, v: float, depth_m: float) -> np.ndarray:
        """Cell-frame point seen at pixel (u, v) at optical depth ``depth_m``."""
        cu, cv = self.centre
        f = self.f_px
        x = (u - cu) * depth_m / f
        y = -(v - cv) * depth_m / f  # image rows grow opposite to +y
        cam_z = BELT_TOP_Z + CAMERA_HEIGHT_ABOVE_BELT
        return np.array([CAMERA_X + x, y, cam_z - depth_m])
