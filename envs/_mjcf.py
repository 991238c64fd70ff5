"""MJCF pieces shared by the task models."""
from __future__ import annotations

from envs._lidar import OBSTACLE_GROUP


def model_xml(
    name: str,
    timestep: float,
    robot: str,
    obstacles: str,
    floor_half_extent: float,
    overview_height: float,
    floor_z: float = 0.0,
    floor_contact: bool = False,
) -> str:
    """A complete MJCF model: defaults, floor, cameras, robot and obstacle bodies.

    Collision filtering: robot geoms have ``contype=1, conaffinity=0``, obstacle geoms
    ``contype=0, conaffinity=1`` and everything else ``0, 0``, so the only pairs
    MuJoCo ever tests are robot-obstacle pairs; with ``floor_contact`` the floor also has
    ``conaffinity=2``, so robot parts with ``contype=2`` (wheels) roll on it without touching
    obstacles or counting as the robot's collision geometry. Visual geoms sit in group 2,
    obstacles in group ``OBSTACLE_GROUP`` (the only group the lidar sees).

    Args:
        name: model name.
        timestep: physics time step (s).
        robot: XML of the robot body (inside ``<worldbody>``) followed by nothing else.
        obstacles: XML of the obstacle mocap bodies.
        floor_half_extent: half size of the drawn floor plane.
        overview_height: height of the top-down ``overview`` camera.
        floor_z: height of the floor plane.
        floor_contact: whether geoms with ``contype=2`` collide with the floor.

    Returns:
        The XML string; append actuators with :func:`with_actuators`.
    """
    return f"""
<mujoco model="{name}">
  <compiler angle="radian"/>
  <option timestep="{timestep}" integrator="Euler" gravity="0 0 -9.81"/>
  <visual>
    <global offwidth="1280" offheight="960"/>
    <quality shadowsize="0"/>
    <headlight ambient="0.45 0.45 0.45" diffuse="0.6 0.6 0.6"/>
  </visual>
  <asset>
    <texture name="grid" type="2d" builtin="checker" rgb1=".82 .84 .86" rgb2=".74 .76 .78" width="256" height="256"/>
    <material name="grid" texture="grid" texrepeat="{floor_half_extent:.6g} {floor_half_extent:.6g}" reflectance="0"/>
  </asset>
  <default>
    <default class="obstacle">
      <geom contype="0" conaffinity="1" group="{OBSTACLE_GROUP}" rgba=".55 .36 .30 1"/>
    </default>
    <default class="robot">
      <geom contype="1" conaffinity="0" group="0" rgba=".2 .5 .9 .25"/>
    </default>
    <default class="visual">
      <geom contype="0" conaffinity="0" group="2" mass="0"/>
    </default>
  </default>
  <worldbody>
    <geom name="floor" class="visual" type="plane" pos="0 0 {floor_z:.6g}"{' conaffinity="2"' if floor_contact else ''}
          size="{floor_half_extent:.6g} {floor_half_extent:.6g} 0.1" material="grid"/>
    <camera name="overview" pos="0 0 {overview_height:.6g}" xyaxes="1 0 0 0 1 0" fovy="60"/>
    {robot}
    {obstacles}
  </worldbody>
"""


def with_actuators(xml: str, actuators: str) -> str:
    """Closes the model started by :func:`model_xml` with an ``<actuator>`` block."""
    return f"{xml}  <actuator>\n{actuators}\n  </actuator>\n</mujoco>\n"
