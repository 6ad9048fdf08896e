"""Builds the MJCF of the factory hall: N conveyor cells laid out from the scenario.

Each cell has a belt, a drop-off platform, a three-axis Cartesian gantry arm with a suction cup
(position servos, gravity compensated), a pool of object bodies recycled as tasks end, and a
downward depth camera. Names are ``c<i>_<part>`` so every node can find its cell's parts.
"""

from __future__ import annotations

from services.common.scenario import Scenario
from services.physics import cell_geometry as g

OBJECT_POOL = 3  # objects per cell; a belt never holds more at the default periods

# Servo gains: stiff enough that the tool lags a 0.2 m/s belt by only a few mm; damping chosen
# near critical for the carriage masses below.
SERVO_KP = 20000.0  # N/m
SERVO_DAMPING = 600.0  # N s/m
SERVO_LAG_S = SERVO_DAMPING / SERVO_KP  # steady-state lag of a position servo to a ramp


def _cell_xml(i: int, x: float, y: float, sc: Scenario) -> tuple[str, str, str]:
    """(worldbody xml, actuator xml, equality xml) of cell ``i`` centred at (x, y)."""
    size = sc.cell.object_size_m
    h = size / 2
    cam_z = g.BELT_TOP_Z + g.CAMERA_HEIGHT_ABOVE_BELT
    px, py = g.PLATFORM_CENTRE
    bl, bw = g.BELT_HALF_LENGTH, g.BELT_HALF_WIDTH
    objects = []
    for k in range(OBJECT_POOL):
        # Parked objects rest on the floor outside the camera's view until spawned.
        objects.append(f"""
    <body name="c{i}_obj{k}" pos="{-0.3 + 0.2 * k} -1.6 {h + 0.001}">
      <freejoint name="c{i}_obj{k}_free"/>
      <geom name="c{i}_obj{k}_geom" type="box" size="{h} {h} {h}" mass="{sc.cell.object_mass_kg}"
            material="part" friction="0.9 0.01 0.001"/>
    </body>""")
    body = f"""
  <body name="c{i}" pos="{x} {y} 0">
    <!-- belt: low friction, the conveyor drive sets object velocity (kinematic belt) -->
    <geom name="c{i}_belt" type="box" pos="0 0 {g.BELT_TOP_Z - 0.05}" size="{bl} {bw} 0.05"
          material="belt" friction="0.05 0.005 0.0001"/>
    <geom name="c{i}_platform" type="box" pos="{px} {py} {g.PLATFORM_TOP_Z - 0.05}"
          size="{g.PLATFORM_HALF} {g.PLATFORM_HALF} 0.05" material="platform"/>
    <geom name="c{i}_post_a" type="cylinder" pos="-0.7 -0.45 {g.GANTRY_Z / 2 + 0.05}"
          size="0.03 {g.GANTRY_Z / 2 + 0.05}" material="frame" contype="0" conaffinity="0"/>
    <geom name="c{i}_post_b" type="cylinder" pos="0.7 -0.45 {g.GANTRY_Z / 2 + 0.05}"
          size="0.03 {g.GANTRY_Z / 2 + 0.05}" material="frame" contype="0" conaffinity="0"/>
    <camera name="c{i}_camera" pos="{g.CAMERA_X} 0 {cam_z}" xyaxes="1 0 0 0 1 0" fovy="{sc.camera.fovy_deg}"/>
    <camera name="c{i}_top" pos="0 0.1 3.2" xyaxes="1 0 0 0 1 0" fovy="45"/>
    <body name="c{i}_gantry" pos="0 0 {g.GANTRY_Z}" gravcomp="1">
      <geom type="box" size="0.75 0.03 0.03" pos="0 -0.45 0.1" material="frame" contype="0" conaffinity="0"/>
      <body name="c{i}_xcar" gravcomp="1">
        <joint name="c{i}_x" type="slide" axis="1 0 0" range="{g.JOINT_RANGES['x'][0]} {g.JOINT_RANGES['x'][1]}"
               damping="{SERVO_DAMPING}" limited="true"/>
        <geom type="box" size="0.04 0.6 0.03" pos="0 0.25 0.1" mass="4" material="frame" contype="0" conaffinity="0"/>
        <body name="c{i}_ycar" gravcomp="1">
          <joint name="c{i}_y" type="slide" axis="0 1 0" range="{g.JOINT_RANGES['y'][0]} {g.JOINT_RANGES['y'][1]}"
                 damping="{SERVO_DAMPING}" limited="true"/>
          <geom type="box" size="0.05 0.05 0.04" pos="0 0 0.1" mass="2" material="frame" contype="0" conaffinity="0"/>
          <body name="c{i}_zcar" gravcomp="1">
            <joint name="c{i}_z" type="slide" axis="0 0 1" range="{g.JOINT_RANGES['z'][0]} {g.JOINT_RANGES['z'][1]}"
                   damping="{SERVO_DAMPING}" limited="true"/>
            <geom type="cylinder" size="0.015 0.25" pos="0 0 0.25" mass="1" material="tool" contype="0" conaffinity="0"/>
            <body name="c{i}_cup" pos="0 0 {-g.CUP_LENGTH / 2}">
              <geom name="c{i}_cup_geom" type="cylinder" size="0.02 {g.CUP_LENGTH / 2}" mass="0.1" material="cup"/>
              <site name="c{i}_tip" pos="0 0 {-g.CUP_LENGTH / 2}" size="0.005"/>
            </body>
          </body>
        </body>
      </body>
    </body>
  </body>
  {''.join(objects)}"""
    act = "".join(
        f'\n    <position name="c{i}_{a}_servo" joint="c{i}_{a}" kp="{SERVO_KP}" '
        f'ctrlrange="{g.JOINT_RANGES[a][0]} {g.JOINT_RANGES[a][1]}" forcerange="-400 400"/>'
        for a in "xyz"
    )
    # One weld per pool object: the suction grip, switched on when the cup seals on a part.
    eq = "".join(
        f'\n    <weld name="c{i}_grip{k}" body1="c{i}_cup" body2="c{i}_obj{k}" active="false"/>'
        for k in range(OBJECT_POOL)
    )
    return body, act, eq


def build_mjcf(sc: Scenario) -> str:
    """The hall with ``sc.loops`` cells, as an MJCF string."""
    bodies, acts, eqs = [], [], []
    for i, (x, y) in enumerate(sc.hall.cell_origins(sc.loops)):
        b, a, e = _cell_xml(i, x, y, sc)
        bodies.append(b)
        acts.append(a)
        eqs.append(e)
    ts = sc.physics_timestep_us / 1e6
    return f"""<mujoco model="cosim5g_hall">
  <compiler angle="radian" autolimits="true"/>
  <option timestep="{ts}" integrator="implicitfast" cone="elliptic"/>
  <visual>
    <global offwidth="{max(sc.camera.width_px, 640)}" offheight="{max(sc.camera.height_px, 480)}"/>
    <quality shadowsize="1024"/>
  </visual>
  <asset>
    <texture name="floor_tex" type="2d" builtin="checker" rgb1=".55 .55 .52" rgb2=".48 .48 .45" width="256" height="256"/>
    <material name="floor" texture="floor_tex" texrepeat="60 30"/>
    <texture name="belt_tex" type="2d" builtin="flat" rgb1=".12 .12 .13" rgb2=".18 .18 .19" mark="random" random="0.3" width="128" height="128"/>
    <material name="belt" texture="belt_tex" texrepeat="6 2"/>
    <material name="platform" rgba=".2 .35 .7 1"/>
    <material name="frame" rgba=".75 .75 .78 1"/>
    <material name="tool" rgba=".3 .3 .3 1"/>
    <material name="cup" rgba=".1 .1 .1 1"/>
    <material name="part" rgba=".95 .45 .05 1"/>
  </asset>
  <worldbody>
    <light name="sun" directional="true" pos="0 0 10" dir="0.2 0.3 -1" diffuse=".8 .8 .8"/>
    <geom name="floor" type="plane" pos="{sc.hall.length_m / 2} {sc.hall.width_m / 2} 0"
          size="{sc.hall.length_m / 2} {sc.hall.width_m / 2} 0.1" material="floor"/>
    {''.join(bodies)}
  </worldbody>
  <actuator>{''.join(acts)}
  </actuator>
  <equality>{''.join(eqs)}
  </equality>
</mujoco>
"""
