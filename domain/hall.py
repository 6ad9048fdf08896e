"""Builds the factory hall: N conveyor cells laid out from the scenario and generated as MJCF,
each with its own copy of the arm (``domain.arm``) attached on its pedestal with mjSpec. Every
name is ``c<i>_<part>``, so each node can find its cell's parts (docs/physics.md)."""

from __future__ import annotations

import math

import mujoco

from domain import work_cell as g
from domain.arm import SERVO_LAG_S, arm_spec
from scenario.schema import Scenario

__all__ = ["SERVO_LAG_S", "build_mjcf", "build_model", "build_spec", "object_pool_size", "park_position"]

# Parts waiting in a cell's pool are parked below the floor, without contacts and with their
# weight compensated, so they cost the solver nothing and no camera sees them.
PARK_Z = -0.5  # m


def object_pool_size(sc: Scenario) -> int:
    """Part bodies per cell of scenario ``sc``: enough for every part on the belt at once (belt
    length / speed, divided by the shortest spawn interval), plus the one in the cup and the one
    settling on the platform."""
    transit_s = 2 * g.BELT_HALF_LENGTH / sc.work_cell.belt_speed_m_s
    shortest_s = sc.work_cell.object_period_s - 2 * sc.work_cell.object_jitter_s
    return math.ceil(transit_s / max(shortest_s, 0.1)) + 2


# The constraint arena of mjData (contacts, constraint rows, solver scratch). MuJoCo's default
# grows with the square of the degrees of freedom: 16 GB of address space for 160 cells of 17 pool
# parts each, more than the host can reserve at 240. What a step uses grows with the cells: 3.6 MB
# for 40 cells with every belt full (60 contacts a cell), so 4 MB a cell leaves a margin of 40x.
ARENA_BASE_MB = 64
ARENA_PER_CELL_MB = 4


def arena_mb(cells: int) -> int:
    """The mjData arena (MB) of a hall of ``cells`` work cells."""
    return ARENA_BASE_MB + ARENA_PER_CELL_MB * cells


def park_position(slot: int) -> tuple[float, float, float]:
    """Where pool slot ``slot`` waits (m, relative to the cell origin)."""
    return (-0.6 + 0.2 * slot, -1.2, PARK_Z)


def _cell_xml(i: int, x: float, y: float, sc: Scenario) -> tuple[str, str]:
    """(worldbody xml, equality xml) of cell ``i`` centred at (x, y), without its arm."""
    h = sc.work_cell.object_size_m / 2
    cam_z = g.BELT_TOP_Z + g.CAMERA_HEIGHT_ABOVE_BELT
    px, py = g.PLATFORM_CENTRE
    bx, by, bz = g.ARM_BASE_POS
    bl, bw = g.BELT_HALF_LENGTH, g.BELT_HALF_WIDTH
    objects = []
    for k in range(object_pool_size(sc)):
        ox, oy, oz = park_position(k)
        # contype/conaffinity 0 and gravcomp 1: parked (the world switches them on at spawn).
        objects.append(f"""
    <body name="c{i}_obj{k}" pos="{x + ox} {y + oy} {oz}" gravcomp="1">
      <freejoint name="c{i}_obj{k}_free"/>
      <geom name="c{i}_obj{k}_geom" type="box" size="{h} {h} {h}" mass="{sc.work_cell.object_mass_kg}"
            material="part" friction="0.9 0.01 0.001" contype="0" conaffinity="0"/>
    </body>""")
    body = f"""
  <body name="c{i}" pos="{x} {y} 0">
    <!-- belt: the conveyor drive sets the parts' velocity every step (kinematic belt), so its
         contacts need no friction: condim 1 (normal force only; priority makes the belt's contact
         parameters win) costs a third of the solver rows of a frictional contact -->
    <geom name="c{i}_belt" type="box" pos="0 0 {g.BELT_TOP_Z - 0.05}" size="{bl} {bw} 0.05"
          material="belt" condim="1" priority="1"/>
    <geom name="c{i}_belt_frame" type="box" pos="0 0 {(g.BELT_TOP_Z - 0.1) / 2}"
          size="{bl - 0.05} {bw - 0.03} {(g.BELT_TOP_Z - 0.1) / 2}" material="frame" contype="0" conaffinity="0"/>
    <geom name="c{i}_platform" type="box" pos="{px} {py} {g.PLATFORM_TOP_Z - 0.05}"
          size="{g.PLATFORM_HALF} {g.PLATFORM_HALF} 0.05" material="platform"/>
    <geom name="c{i}_platform_leg" type="box" pos="{px} {py} {(g.PLATFORM_TOP_Z - 0.1) / 2}"
          size="0.04 0.04 {(g.PLATFORM_TOP_Z - 0.1) / 2}" material="frame" contype="0" conaffinity="0"/>
    <geom name="c{i}_pedestal" type="cylinder" pos="{bx} {by} {bz / 2}" size="{g.PEDESTAL_RADIUS} {bz / 2}"
          material="frame" contype="0" conaffinity="0"/>
    <camera name="c{i}_camera" pos="{g.CAMERA_X} 0 {cam_z}" xyaxes="1 0 0 0 1 0" fovy="{sc.camera.fovy_deg}"/>
    <camera name="c{i}_top" pos="0.05 0.15 3.0" xyaxes="1 0 0 0 1 0" fovy="45"/>
  </body>
  {''.join(objects)}"""
    # One weld per pool part: the suction grip, switched on when the cup seals on a part.
    eq = "".join(
        f'\n    <weld name="c{i}_grip{k}" body1="c{i}_cup" body2="c{i}_obj{k}" active="false"/>'
        for k in range(object_pool_size(sc))
    )
    return body, eq


def _hall_xml(sc: Scenario) -> str:
    bodies, eqs = [], []
    for i, (x, y) in enumerate(sc.hall.work_cell_origins(sc.loops)):
        b, e = _cell_xml(i, x, y, sc)
        bodies.append(b)
        eqs.append(e)
    ts = sc.physics_timestep_us / 1e6
    return f"""<mujoco model="cosim5g_hall">
  <compiler angle="radian" autolimits="true"/>
  <!-- sleep: parked pool parts sleep, so stepping skips them (World._may_sleep) -->
  <option timestep="{ts}" integrator="implicitfast" cone="elliptic">
    <flag sleep="enable"/>
  </option>
  <visual>
    <global offwidth="{max(sc.camera.width_px, 640)}" offheight="{max(sc.camera.height_px, 480)}"/>
    <quality shadowsize="1024"/>
    <!-- near clip 5 cm: the arm may pass close under the cell camera -->
    <map znear="0.05" zfar="100"/>
  </visual>
  <size memory="{arena_mb(sc.loops)}M"/>
  <statistic extent="1" center="0 0 0.8"/>
  <asset>
    <texture name="floor_tex" type="2d" builtin="checker" rgb1=".55 .55 .52" rgb2=".48 .48 .45" width="256" height="256"/>
    <material name="floor" texture="floor_tex" texrepeat="60 30"/>
    <texture name="belt_tex" type="2d" builtin="flat" rgb1=".12 .12 .13" rgb2=".18 .18 .19" mark="random" random="0.3" width="128" height="128"/>
    <material name="belt" texture="belt_tex" texrepeat="6 2"/>
    <material name="platform" rgba=".2 .35 .7 1"/>
    <material name="frame" rgba=".55 .57 .6 1"/>
    <material name="part" rgba=".95 .45 .05 1"/>
  </asset>
  <worldbody>
    <light name="sun" directional="true" pos="0 0 10" dir="0.2 0.3 -1" diffuse=".8 .8 .8"/>
    <geom name="floor" type="plane" pos="{sc.hall.length_m / 2} {sc.hall.width_m / 2} 0"
          size="{sc.hall.length_m / 2} {sc.hall.width_m / 2} 0.1" material="floor"/>
    {''.join(bodies)}
  </worldbody>
  <equality>{''.join(eqs)}
  </equality>
</mujoco>
"""


def build_spec(sc: Scenario) -> mujoco.MjSpec:
    """The hall with ``sc.loops`` cells, each with its own copy of the arm, as an mjSpec."""
    spec = mujoco.MjSpec.from_string(_hall_xml(sc))
    spec.copy_during_attach = True  # one spec of the arm, attached (copied) into every cell
    arm = arm_spec()
    yaw = g.ARM_BASE_YAW
    quat = [math.cos(yaw / 2), 0.0, 0.0, math.sin(yaw / 2)]
    for i in range(sc.loops):
        frame = spec.body(f"c{i}").add_frame(pos=list(g.ARM_BASE_POS), quat=quat)
        spec.attach(arm, prefix=f"c{i}_", frame=frame)
    return spec


def build_model(sc: Scenario) -> mujoco.MjModel:
    """The compiled hall of scenario ``sc``."""
    return build_spec(sc).compile()


def build_mjcf(sc: Scenario) -> str:
    """The hall of scenario ``sc`` as one self-contained MJCF string (for inspection and the
    model tests)."""
    return build_spec(sc).to_xml()
