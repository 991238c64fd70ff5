"""Multirotor pieces shared by ``quadrotor_nav`` and ``hexarotor_wind``.

The multirotor is a free body (collision sphere of radius ``robot_radius``) with a
velocity-tracking inner loop made of MuJoCo actuators that run at every 0.02 s
physics step: per world axis a velocity servo (time constant 50 ms) whose force is
saturated at ``mass * 8`` N (so braking from 5 m/s per axis takes ~0.8 s), plus
gravity compensation (hover thrust, MuJoCo ``gravcomp``). ``max_acceleration=None``
(an argument of the tasks' ``build_environment`` and of :func:`envs.make`) removes the
force limit: each servo is then linear, ``v+ = 0.6^5 v + (1 - 0.6^5) u`` per 0.1 s
control step away from contacts (explicit Euler at 0.02 s), plus the noise (and, for
``hexarotor_wind``, the wind drag, also linear in the velocity). Attitude is not
simulated: the body stays level and the lidar is world-aligned. The action is the
commanded velocity ``[-5, 5]^3`` m/s held for 0.1 s.

The arena is ``20 m × 20 m × 6 m``: floor, ceiling and four walls are obstacles
(the first six of ``K``), followed by random upright cylinders (floor-to-ceiling
pillars) and random yawed boxes floating at random heights.
"""
from __future__ import annotations

from typing import ClassVar

import numpy as np

from envs._lidar import Lidar, rings
from envs._mjcf import model_xml, with_actuators
from envs._obstacles import Obstacle, boundary_walls, obstacle_bodies_xml
from envs._task import GoalTask

ARENA = 10.0
CEILING = 6.0
MAX_COMMAND = 5.0
MAX_ACCELERATION = 8.0
LIDAR_RANGE = 10.0
N_BOUNDARY = 6
_SLAB = 0.5
_PILLAR_RADIUS = (0.3, 0.8)
_BOX_HALF_SIDE = (0.3, 1.5)
_BOX_HALF_HEIGHT = (0.3, 1.5)
_SERVO_TIME_CONSTANT = 0.05


def boundary() -> list[Obstacle]:
    """Floor, ceiling and four walls enclosing ``|x|, |y| ≤ 10, 0 ≤ z ≤ 6``."""
    half = ARENA + _SLAB
    floor = Obstacle("box", np.array([0.0, 0.0, -_SLAB / 2]), np.array([half, half, _SLAB / 2]))
    ceiling = Obstacle("box", np.array([0.0, 0.0, CEILING + _SLAB / 2]), np.array([half, half, _SLAB / 2]))
    return [floor, ceiling] + boundary_walls(ARENA, _SLAB, CEILING + 2 * _SLAB, CEILING / 2)


def draw_obstacle(rng: np.random.RandomState, kind: str) -> Obstacle:
    """A random pillar (``"cylinder"``) or floating yawed box inside the arena."""
    xy = rng.uniform(-ARENA + 1.0, ARENA - 1.0, 2)
    if kind == "cylinder":
        radius = rng.uniform(*_PILLAR_RADIUS)
        return Obstacle("cylinder", np.array([*xy, CEILING / 2]), np.array([radius, radius, CEILING / 2]))
    half = np.array([*rng.uniform(*_BOX_HALF_SIDE, 2), rng.uniform(*_BOX_HALF_HEIGHT)])
    z = rng.uniform(half[2], CEILING - half[2])
    return Obstacle("box", np.array([*xy, z]), half, yaw=rng.uniform(0, np.pi))


class AerialTask(GoalTask):
    """Shared multirotor task logic; subclasses add goals, wind and observations.

    State ``(x, y, z, vx, vy, vz)`` (world frame); process noise
    ``U[-0.02, 0.02]`` m/s on each velocity.
    """

    obstacle_dim = 3
    action_low = np.full(3, -MAX_COMMAND)
    action_high = np.full(3, MAX_COMMAND)
    noise_center = np.zeros(6)
    noise_generators = np.concatenate([np.zeros((3, 3)), 0.02 * np.eye(3)])
    position_dims = (0, 1, 2)
    velocity_dims = (3, 4, 5)
    start = np.array([0.0, 0.0, 2.0])
    #: data region of the empty variant: ``|x|, |y| ≤ 10``, ``-4 ≤ z ≤ 8``
    data_region_low = np.array([-ARENA, -ARENA, -4.0])
    data_region_high = np.array([ARENA, ARENA, 8.0])
    # the zero command stops either multirotor within 10 steps (for ``hexarotor_wind`` in any wind: the
    # integral offset cancels the drag)
    n_brk = 10
    n_plan = 11
    braking_action = np.zeros(3)
    stop_tolerance = 0.05
    n_pillars: ClassVar[int]
    n_boxes: ClassVar[int]
    mass: ClassVar[float]
    n_rotors: ClassVar[int]

    @classmethod
    def model(cls, empty: bool, max_acceleration: float | None = MAX_ACCELERATION) -> str:
        """The MJCF model of this multirotor (see :func:`aerial_model`)."""
        return aerial_model(cls.name, empty, cls.n_pillars, cls.n_boxes, cls.robot_radius, cls.mass, cls.n_rotors,
                            max_acceleration)

    def _bind(self, physics) -> None:
        model = physics.model
        self._body = model.name2id("robot", "body")
        self._lidar = Lidar(rings(8, np.deg2rad([-25.0, 25.0])), LIDAR_RANGE, self._body)
        if self._slots is not None:  # see-through floor and ceiling slabs (still hit by the lidar)
            model.geom_rgba[self._slots.geom_ids[:2]] = [0.8, 0.8, 0.8, 0.05]

    def _reset_robot(self, physics, rng) -> None:
        physics.data.qpos[:3] = self.start
        physics.data.qpos[3:7] = [1.0, 0.0, 0.0, 0.0]
        if self.empty:
            physics.data.qvel[:3] = self.random.uniform(-MAX_COMMAND, MAX_COMMAND, 3)

    def _apply_action(self, action, physics) -> None:
        physics.data.ctrl[:] = action

    def _add_state_noise(self, physics, noise) -> None:
        physics.data.qvel[:3] += noise[3:6]

    def position(self, physics):
        return physics.data.qpos[:3].copy()

    def state(self, physics):
        return np.concatenate([physics.data.qpos[:3], physics.data.qvel[:3]])

    def _lidar_scan(self, physics) -> np.ndarray:
        return self._lidar.scan(physics, physics.data.qpos[:3]) / LIDAR_RANGE

    def _speed(self, physics) -> float:
        return float(np.linalg.norm(physics.data.qvel[:3]))

    def _in_data_region(self, physics) -> bool:
        position = physics.data.qpos[:3]
        return bool(np.all(position >= self.data_region_low) and np.all(position <= self.data_region_high))


def aerial_model(
    name: str,
    empty: bool,
    n_pillars: int,
    n_boxes: int,
    radius: float,
    mass: float,
    n_rotors: int,
    max_acceleration: float | None = MAX_ACCELERATION,
) -> str:
    """MJCF of a multirotor in the arena (see the module docstring).

    Args:
        name: model name.
        empty: leave out every obstacle body.
        n_pillars: number of random cylinder slots.
        n_boxes: number of random box slots.
        radius: collision sphere radius (m).
        mass: body mass (kg).
        n_rotors: rotors drawn (visual only).
        max_acceleration: force limit of the velocity servos per unit mass (m/s^2);
            ``None``: no limit (linear servos).
    """
    robot = f"""
    <body name="robot" pos="0 0 2" gravcomp="1">
      <freejoint name="root"/>
      <geom name="robot" class="robot" type="sphere" size="{radius}" mass="{mass}"/>
      {airframe_visuals(radius, n_rotors)}
    </body>"""
    xml = arena_xml(name, 0.02, robot, empty, n_pillars, n_boxes)
    kv = mass / _SERVO_TIME_CONSTANT
    if max_acceleration is None:
        limit = 'forcelimited="false"'
    else:
        force = mass * max_acceleration
        limit = f'forcelimited="true" forcerange="{-force:.6g} {force:.6g}"'
    actuators = "\n".join(
        f'    <velocity name="v{axis}" joint="root" gear="{gear}" kv="{kv:.6g}" {limit}/>'
        for axis, gear in (("x", "1 0 0 0 0 0"), ("y", "0 1 0 0 0 0"), ("z", "0 0 1 0 0 0"))
    )
    return with_actuators(xml, actuators)


def airframe_visuals(radius: float, n_rotors: int) -> str:
    """Visual geoms of a multirotor of collision radius ``radius``: hub, ``n_rotors`` arms of length
    ``0.8 * radius`` (rotor ``i`` at the angle ``(i + 0.5) 2π / n_rotors``) with propeller discs, and the
    ``follow`` camera."""
    arm = 0.8 * radius
    visuals = [f'<geom class="visual" type="box" size="{0.25 * radius:.4f} {0.25 * radius:.4f} 0.04"'
               ' rgba=".9 .35 .2 1"/>']
    for i in range(n_rotors):
        angle = (i + 0.5) * 2 * np.pi / n_rotors
        x, y = arm * np.cos(angle), arm * np.sin(angle)
        visuals.append(
            f'<geom class="visual" type="capsule" fromto="0 0 0 {x:.4f} {y:.4f} 0" size="0.02" rgba=".15 .15 .17 1"/>'
            f'<geom class="visual" type="cylinder" pos="{x:.4f} {y:.4f} 0.03" size="{0.35 * radius:.4f} 0.004"'
            ' rgba=".6 .6 .65 .6"/>'
        )
    visuals.append('<camera name="follow" mode="trackcom" pos="0 -6 5" xyaxes="1 0 0 0 0.8 0.6"/>')
    return "\n      ".join(visuals)


def arena_xml(name: str, timestep: float, robot: str, empty: bool, n_pillars: int, n_boxes: int) -> str:
    """The arena model around a multirotor body ``robot`` (XML of ``<body name="robot">``), without actuators.

    Args:
        name: model name.
        timestep: physics time step (s).
        robot: the robot body's XML.
        empty: leave out every obstacle body.
        n_pillars: number of random cylinder slots.
        n_boxes: number of random box slots.

    Returns:
        The XML string; close it with :func:`envs._mjcf.with_actuators`.
    """
    kinds = ("box",) * N_BOUNDARY + ("cylinder",) * n_pillars + ("box",) * n_boxes
    max_half = [o.half_size for o in boundary()]
    max_half += [[_PILLAR_RADIUS[1], _PILLAR_RADIUS[1], CEILING / 2]] * n_pillars
    max_half += [[_BOX_HALF_SIDE[1], _BOX_HALF_SIDE[1], _BOX_HALF_HEIGHT[1]]] * n_boxes
    obstacles = "" if empty else obstacle_bodies_xml(kinds, max_half)
    return model_xml(name, timestep, robot, obstacles, floor_half_extent=ARENA + 1.0, overview_height=19.0,
                     floor_z=-0.01)
