"""Geometry of one conveyor cell, in the cell frame (origin on the floor at the cell centre, x along
the belt, z up). Shared by the scene builder, the robot controller and the Edge so that every
node agrees on where the belt, the platform and the camera are (as a calibrated real cell would).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

BELT_TOP_Z = 0.75  # m, belt surface height: a common working height
BELT_HALF_LENGTH = 0.6  # m, belt runs x in [-0.6, 0.6]
BELT_HALF_WIDTH = 0.2  # m
SPAWN_X = -0.55  # m, objects appear at the upstream end
PICK_X_RANGE = (-0.40, 0.45)  # m, stretch of belt where the arm may grasp (inside its reach)

# Drop-off platform: beside the belt on the arm's side (5 cm gap to the belt edge), at the upstream
# end: after a place the cup is already next to where the next part enters the pick window, which
# takes about a second off the pick-and-place cycle compared with a platform downstream.
PLATFORM_CENTRE = (-0.45, 0.40)  # m
PLATFORM_HALF = 0.15  # m, platform is 0.3 x 0.3 m
PLATFORM_TOP_Z = 0.75  # m

# The arm (domain/models/arm6.xml) stands on a pedestal beside the belt, opposite the
# middle of the pick window. 0.55 m from the belt axis and 5 cm above the belt keeps every pick
# point, the platform and the straight moves between them well inside the reach of a UR5e-class
# arm and away from its singularities (smallest Jacobian singular value >= 0.065 on those paths).
ARM_BASE_POS = (0.0, 0.55, 0.80)  # m, base mounting flange centre (cell frame)
ARM_BASE_YAW = math.pi / 2  # rad, base x axis along cell +y
PEDESTAL_RADIUS = 0.09  # m
# Tool orientation for every pick and place: a rotation matrix (cell frame, given by rows; its
# columns are the tool x, y, z axes). The cup points straight down (tool z = -z) and the tool's
# angle bracket points from the flange towards the belt axis (tool x = -y), so the wrist stays on
# the arm's side of the part it is picking.
TOOL_DOWN = ((0.0, -1.0, 0.0), (-1.0, 0.0, 0.0), (0.0, 0.0, -1.0))
# Where the cup waits for the next part: above the upstream end of the pick window, beside the
# parts' path so that it does not hide them from the camera.
HOME_TOOL_POS = (-0.30, 0.15, 1.00)  # m

CAMERA_HEIGHT_ABOVE_BELT = 1.0  # m, camera looks straight down at the belt centre
CAMERA_X = 0.0  # m


@dataclass(frozen=True)
class CameraIntrinsics:
    """Pinhole intrinsics of a downward camera of ``width`` x ``height`` px and vertical field
    of view ``fovy_deg`` (deg); pixel (u, v) with v growing downwards."""

    width: int
    height: int
    fovy_deg: float

    @property
    def f_px(self) -> float:
        """Focal length (px)."""
        return (self.height / 2) / np.tan(np.radians(self.fovy_deg) / 2)

    @property
    def centre(self) -> tuple[float, float]:
        """Principal point (u, v) (px): the image centre."""
        return ((self.width - 1) / 2, (self.height - 1) / 2)

    def back_project(self, u: float, v: float, depth_m: float) -> np.ndarray:
        """Cell-frame point (m) seen at pixel (``u``, ``v``) (px) at optical depth ``depth_m``
        (m)."""
        cu, cv = self.centre
        f = self.f_px
        x = (u - cu) * depth_m / f
        y = -(v - cv) * depth_m / f  # image rows grow opposite to +y
        cam_z = BELT_TOP_Z + CAMERA_HEIGHT_ABOVE_BELT
        return np.array([CAMERA_X + x, y, cam_z - depth_m])
