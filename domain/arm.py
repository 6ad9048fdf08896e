"""The 6-DOF arm of every cell: where its model is, its joint names, its drives' limits and the
servo lag the controller compensates. The model itself is ``models/arm6.xml`` (UR5e-class DH
kinematics and masses, position servos, vacuum tool); the scene attaches it once per cell.
"""

from __future__ import annotations

import math
from pathlib import Path

import mujoco

ARM_XML = Path(__file__).parent / "models" / "arm6.xml"
JOINTS = ("shoulder_pan", "shoulder_lift", "elbow", "wrist_1", "wrist_2", "wrist_3")
N_JOINTS = len(JOINTS)
CUP_BODY = "cup"  # the tool body the suction weld holds a part to
TCP_SITE = "tcp"  # centre of the suction cup's lip
CUP_RADIUS_M = 0.015  # lip radius of the bellows cup

# Every servo in arm6.xml has kv / kp = 0.02 s: a joint tracking a ramp lags it by this time.
SERVO_LAG_S = 0.02
JOINT_SPEED_MAX_RAD_S = math.radians(180.0)  # vendor figure for this arm class, every joint
TCP_SPEED_MAX_M_S = 1.0  # vendor figure for this arm class

# Rest posture: the cup at work_cell.HOME_TOOL_POS, pointing down (TOOL_DOWN), elbow up.
# The IK solution for that pose with the base at ARM_BASE_POS / ARM_BASE_YAW (a unit test checks
# that they agree).
HOME_Q = (-1.1050, -1.7121, 2.1009, -1.9596, -1.5708, -2.6758)


def arm_spec() -> mujoco.MjSpec:
    """A fresh, editable spec of the arm (to attach into a scene)."""
    return mujoco.MjSpec.from_file(str(ARM_XML))


def arm_model() -> mujoco.MjModel:
    """The arm alone, base at the origin: the robot node's own model for kinematics."""
    return mujoco.MjModel.from_xml_path(str(ARM_XML))
