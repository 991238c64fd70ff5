"""``diffdrive_nav``: a Turtlebot-3-like differential-drive robot navigating to a goal.

* Robot (``robot="kinematic"``, the default): collision sphere of radius 0.11 m (the planar
  footprint is the disc of that radius) on joints x, y, yaw; mass 1 kg, yaw inertia 0.01 kg m^2. The action
  ``(v, ω) ∈ [0, 0.25] m/s × [-0.5, 0.5] rad/s`` is held for 0.1 s and tracked by
  MuJoCo velocity servos at every 0.02 s physics step: body-frame forward speed
  (time constant 50 ms, acceleration limit 0.5 m/s^2), yaw rate (50 ms, 2 rad/s^2)
  and a stiff zero-lateral-speed servo standing in for wheel grip. Braking from
  full speed takes 5-6 control steps. ``max_acceleration=None`` and
  ``max_turn_acceleration=None`` (arguments of :func:`build_environment` and
  :func:`envs.make`) remove the two acceleration limits: the speed and yaw-rate servos
  are then linear and braking takes 3 steps, so only the planar kinematics
  (``v cos θ``, ``v sin θ``) stay nonlinear for a fitted linear model.
* Wheeled robot (``robot="wheeled"``): the same collision sphere on a chassis with joints x, y,
  yaw and z (no roll or pitch), two driven wheels on hinges (radius ``WHEEL_RADIUS`` 0.033 m,
  track ``TRACK`` 0.16 m, 0.05 kg each, armature 0.001 kg m^2 for the geared motor, which also
  keeps MuJoCo's soft friction from letting the light wheels slip) rolling on the floor with
  friction 1, and a frictionless caster ball 0.08 m behind the axle; 1 kg in all, chassis yaw
  inertia 0.01 kg m^2. The wheels' collision spheres touch only the floor, so obstacle contacts and
  the footprint stay the chassis sphere's. Its wheel controller, run by MuJoCo at every 5 ms physics
  step (20 per control step): the command becomes wheel speeds ``(v ∓ ω TRACK / 2) / WHEEL_RADIUS``;
  each wheel's setpoint ramps towards its target at ``WHEEL_ACCELERATION`` = 18 rad/s^2
  (0.59 m/s^2 at the rim; the setpoint is the actuator's activation, an integrator of ``±18``
  whose range ends at the target), and a velocity servo (gain 0.3 N m s/rad, torque limit
  ``WHEEL_TORQUE`` 0.5 N m) tracks it. The ramps restart every control step from the wheel
  speeds of the measured ``(v, ω)``, so the controller has no memory beyond the state below.
  Measured braking (zero command): 5 steps from full forward speed, 6 from ``(0.25, ±0.5)``, 1 from
  a pure full turn; at most 6 from 400 random reachable states. Process noise kicks the chassis
  and spins the wheels along (rolling), so it changes ``v`` and ``ω`` by exactly the noise.
  Same spaces, noise, :func:`envs.safety_info` and layouts as the kinematic robot; about half its steps/s.
* State ``(x, y, cos θ, sin θ, v, ω)`` with ``v`` the body-frame forward speed;
  process noise ``U[-0.005, 0.005]`` m/s on ``v`` and ``U[-0.01, 0.01]`` rad/s on ``ω``.
* Observation (23): 18 lidar ranges over the front 180° divided by the 3.5 m range,
  goal distance, cos/sin of the goal bearing in the robot frame, ``v``, ``ω``.
* Layout: 5 m × 5 m arena (four walls), 4 random cylinders and 4 random yawed
  boxes, a goal disc (radius 0.2 m) 1.2-2.0 m from the start at the centre,
  random start heading. ``K = 12`` obstacles, ``p = 6`` generators.
* Ends at the goal or a collision (``terminated``) or after 300 steps (``truncated``).
* Empty variant: no walls or obstacles, random start speeds, truncated when
  ``|x|`` or ``|y|`` exceeds 2.5 m.
"""
from __future__ import annotations

import numpy as np
from dm_control.rl import control

from envs._lidar import Lidar, planar_fan
from envs._mjcf import model_xml, with_actuators
from envs._obstacles import KeepOut, Layout, Obstacle, boundary_walls, obstacle_bodies_xml, place_obstacles
from envs._task import GoalTask, task_environment

ARENA = 2.5
MAX_SPEED = 0.25
MAX_TURN_RATE = 0.5
LIDAR_RANGE = 3.5
N_LIDAR = 18
GOAL_RADIUS = 0.2
ROBOTS = ("kinematic", "wheeled")
MAX_ACCELERATION = 0.5
MAX_TURN_ACCELERATION = 2.0
WHEEL_RADIUS = 0.033
TRACK = 0.16
WHEEL_ACCELERATION = 18.0
WHEEL_TORQUE = 0.5
WHEELED_TIMESTEP = 0.005
_MASS = 1.0
_WHEEL_MASS = 0.05
_WHEEL_KV = 0.3
_WHEEL_ARMATURE = 1e-3
_CASTER_RADIUS = 0.02
_CASTER_X = -0.08
_SETTLED_Z = -1.1e-4  # the wheeled chassis' rest height offset: the contacts' sag under its weight
_YAW_INERTIA = 0.01
_HEIGHT = 0.4
_ROBOT_Z = 0.15
_WALL_THICKNESS = 0.2
_N_CYLINDERS = 4
_N_BOXES = 4
_CYLINDER_RADIUS = (0.1, 0.25)
_BOX_HALF_SIDE = (0.1, 0.3)


def _walls() -> list[Obstacle]:
    return boundary_walls(ARENA, _WALL_THICKNESS, _HEIGHT, _HEIGHT / 2)


class DiffDriveNav(GoalTask):
    """The dm_control task of ``diffdrive_nav`` (see the module docstring).

    Examples:
        >>> env = build_environment(seed=0)
        >>> env.reset().observation["observation"].shape
        (23,)
    """

    name = "diffdrive_nav"
    layout_code = 2
    obstacle_dim = 2
    capacity = 4 + _N_CYLINDERS + _N_BOXES
    robot_radius = 0.11
    observation_dim = N_LIDAR + 5
    action_low = np.array([0.0, -MAX_TURN_RATE])
    action_high = np.array([MAX_SPEED, MAX_TURN_RATE])
    noise_center = np.zeros(6)
    noise_generators = np.array([[0, 0], [0, 0], [0, 0], [0, 0], [0.005, 0], [0, 0.01]], dtype=np.float64)
    position_dims = (0, 1)
    heading_dims = (2, 3)
    velocity_dims = (4, 5)
    obstacle_kinds = ("box",) * 4 + ("cylinder",) * _N_CYLINDERS + ("box",) * _N_BOXES
    progress_scale = 10.0
    episode_steps = 300
    n_brk = 6  # either robot, from any reachable speed, with the default acceleration limits
    n_plan = 8
    braking_action = np.zeros(2)
    stop_tolerance = 0.02

    def _bind(self, physics) -> None:
        self._lidar = Lidar(planar_fan(N_LIDAR, np.pi), LIDAR_RANGE, physics.model.name2id("robot", "body"))

    def _draw_obstacle(self, rng, kind: str) -> Obstacle:
        pos = np.array([*rng.uniform(-ARENA + 0.3, ARENA - 0.3, 2), _HEIGHT / 2])
        if kind == "cylinder":
            radius = rng.uniform(*_CYLINDER_RADIUS)
            return Obstacle("cylinder", pos, np.array([radius, radius, _HEIGHT / 2]))
        half = rng.uniform(*_BOX_HALF_SIDE, 2)
        return Obstacle("box", pos, np.array([*half, _HEIGHT / 2]), yaw=rng.uniform(0, np.pi))

    def _new_layout(self, rng):
        angle, distance = rng.uniform(0, 2 * np.pi), rng.uniform(1.2, 2.0)
        goal = distance * np.array([np.cos(angle), np.sin(angle)])
        self._heading = rng.uniform(-np.pi, np.pi)
        obstacles = []
        if not self.empty:
            keep_out = [
                KeepOut(np.zeros(2), clearance=self.robot_radius + 0.4),
                KeepOut(goal, clearance=GOAL_RADIUS + self.robot_radius + 0.15),
            ]
            obstacles = _walls() + place_obstacles(rng, self._draw_obstacle, self.obstacle_kinds[4:], keep_out)
        center, generators, mask = self._layout_zonotopes(obstacles)
        half = ARENA + _WALL_THICKNESS
        return Layout(
            obstacles=tuple(obstacles),
            obstacle_center=center,
            obstacle_generators=generators,
            obstacle_mask=mask,
            goals=goal[None],
            goal_radius=GOAL_RADIUS,
            start=np.zeros(2),
            extent=(-half, half, -half, half),
        )

    def _reset_robot(self, physics, rng) -> None:
        physics.data.qpos[:3] = [0.0, 0.0, self._heading]
        if self.empty:
            speed = self.random.uniform(0.0, MAX_SPEED)
            self._add_velocity(physics, speed, self.random.uniform(-MAX_TURN_RATE, MAX_TURN_RATE))

    def _add_velocity(self, physics, speed: float, turn_rate: float) -> None:
        """Adds a body-frame forward speed and a yaw rate to the robot's velocity."""
        heading = physics.data.qpos[2]
        physics.data.qvel[:2] += speed * np.array([np.cos(heading), np.sin(heading)])
        physics.data.qvel[2] += turn_rate

    def _apply_action(self, action, physics) -> None:
        physics.data.ctrl[:] = [action[0], 0.0, action[1]]

    def _add_state_noise(self, physics, noise) -> None:
        self._add_velocity(physics, noise[4], noise[5])

    def position(self, physics):
        return physics.data.qpos[:2].copy()

    def state(self, physics):
        x, y, heading = physics.data.qpos[:3]
        vx, vy, turn_rate = physics.data.qvel[:3]
        cos, sin = np.cos(heading), np.sin(heading)
        return np.array([x, y, cos, sin, cos * vx + sin * vy, turn_rate])

    def _policy_observation(self, physics):
        x, y, heading = physics.data.qpos[:3]
        ranges = self._lidar.scan(physics, np.array([x, y, _ROBOT_Z]), heading)
        offset = self.current_goal() - np.array([x, y])
        bearing = np.arctan2(offset[1], offset[0]) - heading
        state = self.state(physics)
        return np.concatenate(
            [ranges / LIDAR_RANGE, [np.linalg.norm(offset), np.cos(bearing), np.sin(bearing)], state[4:]]
        )

    def _speed(self, physics) -> float:
        return float(np.linalg.norm(physics.data.qvel[:2]))

    def _in_data_region(self, physics) -> bool:
        return bool(np.all(np.abs(physics.data.qpos[:2]) <= ARENA))


def wheel_speeds(speed, turn_rate) -> np.ndarray:
    """Left and right wheel speeds (rad/s) of a body-frame forward speed and yaw rate, shape ``[2]``."""
    return (speed + np.array([-0.5, 0.5]) * TRACK * turn_rate) / WHEEL_RADIUS


class WheeledDiffDriveNav(DiffDriveNav):
    """``diffdrive_nav`` with the wheeled robot (``robot="wheeled"``, see the module docstring).

    The wheel controller keeps no memory between control steps: its ramps restart from the wheel
    speeds of the measured ``(v, ω)``, so the 6-D state stays the state of the controlled robot.

    Examples:
        >>> env = build_environment(robot="wheeled", seed=0)
        >>> env.reset().observation["state"].shape
        (6,)
    """

    def _reset_robot(self, physics, rng) -> None:
        physics.data.qpos[3] = _SETTLED_Z
        super()._reset_robot(physics, rng)

    def _add_velocity(self, physics, speed: float, turn_rate: float) -> None:
        """Adds the velocity to the chassis and the matching spin to the wheels (rolling, no slip)."""
        super()._add_velocity(physics, speed, turn_rate)
        physics.data.qvel[4:6] += wheel_speeds(speed, turn_rate)

    def _apply_action(self, action, physics) -> None:
        """Starts the wheel-speed ramps: the actuator activation integrates ``±WHEEL_ACCELERATION``
        from the measured speeds and stops at the commanded ones (its range ends there)."""
        start = wheel_speeds(*self.state(physics)[4:])
        target = wheel_speeds(*action)
        physics.data.act[:] = start
        physics.data.ctrl[:] = WHEEL_ACCELERATION * np.sign(target - start)
        physics.model.actuator_actrange[:] = np.sort([start, target], axis=0).T


#: the task class of each robot (``robot`` of :func:`build_environment`)
ROBOT_TASKS = {"kinematic": DiffDriveNav, "wheeled": WheeledDiffDriveNav}


def _force_limit(limit: float | None) -> str:
    return 'forcelimited="false"' if limit is None else f'forcelimited="true" forcerange="{-limit:.6g} {limit:.6g}"'


_CHASSIS_VISUALS = """
      <geom class="visual" type="cylinder" size="0.09 0.07" pos="-0.02 0 -0.02" rgba=".15 .15 .17 1"/>
      <geom class="visual" type="cylinder" size="0.035 0.02" pos="0 0 0.07" rgba=".2 .2 .2 1"/>
      <geom class="visual" type="box" size="0.03 0.01 0.005" pos="0.06 0 0.055" rgba=".9 .3 .2 1"/>
      <site name="base"/>
      <camera name="follow" mode="trackcom" pos="0 -1.5 2" xyaxes="1 0 0 0 0.8 0.6"/>"""
_PLANAR_JOINTS = """<joint name="x" type="slide" axis="1 0 0"/>
      <joint name="y" type="slide" axis="0 1 0"/>
      <joint name="yaw" type="hinge" axis="0 0 1"/>"""
_WHEEL_VISUAL = f'type="cylinder" size="{WHEEL_RADIUS} 0.009" euler="1.5708 0 0" rgba="0 0 0 1"'


def _obstacles_xml(empty: bool) -> str:
    """The obstacle mocap bodies, sized for the largest obstacles of each slot (none when ``empty``)."""
    if empty:
        return ""
    max_half = [w.half_size for w in _walls()]
    max_half += [[_CYLINDER_RADIUS[1], _CYLINDER_RADIUS[1], _HEIGHT / 2]] * _N_CYLINDERS
    max_half += [[_BOX_HALF_SIDE[1], _BOX_HALF_SIDE[1], _HEIGHT / 2]] * _N_BOXES
    return obstacle_bodies_xml(DiffDriveNav.obstacle_kinds, max_half)


def _model(empty: bool, max_acceleration: float | None, max_turn_acceleration: float | None) -> str:
    """The kinematic robot: chassis velocity servos on joints x, y, yaw."""
    robot = f"""
    <body name="robot" pos="0 0 {_ROBOT_Z}">
      {_PLANAR_JOINTS}
      <inertial pos="0 0 0" mass="{_MASS}" diaginertia="{_YAW_INERTIA} {_YAW_INERTIA} {_YAW_INERTIA}"/>
      <geom name="robot" class="robot" type="sphere" size="{DiffDriveNav.robot_radius}"/>
      <geom class="visual" {_WHEEL_VISUAL} pos="0 {TRACK / 2:.6g} {WHEEL_RADIUS - _ROBOT_Z:.6g}"/>
      <geom class="visual" {_WHEEL_VISUAL} pos="0 {-TRACK / 2:.6g} {WHEEL_RADIUS - _ROBOT_Z:.6g}"/>{_CHASSIS_VISUALS}
    </body>"""
    xml = model_xml("diffdrive_nav", 0.02, robot, _obstacles_xml(empty), floor_half_extent=3.0, overview_height=5.0)
    forward = _force_limit(None if max_acceleration is None else _MASS * max_acceleration)
    turn = _force_limit(None if max_turn_acceleration is None else _YAW_INERTIA * max_turn_acceleration)
    return with_actuators(
        xml,
        f"""    <velocity name="forward" site="base" gear="1 0 0 0 0 0" kv="20" {forward}/>
    <velocity name="lateral" site="base" gear="0 1 0 0 0 0" kv="40" {_force_limit(5.0)}/>
    <velocity name="turn" joint="yaw" kv="0.2" {turn}/>""",
    )


def _wheel(side: str, y: float) -> str:
    """A driven wheel on a hinge about the body y axis: a visual tyre and a collision sphere of the wheel's
    radius (one rolling contact, no scrub) that only touches the floor."""
    return f"""
      <body name="{side}_wheel" pos="0 {y:.6g} {WHEEL_RADIUS - _ROBOT_Z:.6g}">
        <joint name="{side}_wheel" type="hinge" axis="0 1 0" armature="{_WHEEL_ARMATURE}"/>
        <geom type="sphere" size="{WHEEL_RADIUS}" mass="{_WHEEL_MASS}" contype="2" conaffinity="0" group="3"/>
        <geom class="visual" {_WHEEL_VISUAL}/>
      </body>"""


def _wheel_actuator(side: str) -> str:
    """Velocity servo on the ramped wheel-speed setpoint (its activation), torque-limited."""
    return (f'    <general name="{side}" joint="{side}_wheel" dyntype="integrator" actlimited="true" actrange="-1 1"'
            f' gainprm="{_WHEEL_KV}" biastype="affine" biasprm="0 0 {-_WHEEL_KV}" {_force_limit(WHEEL_TORQUE)}/>')


def _wheeled_model(empty: bool) -> str:
    """The wheeled robot: chassis on joints x, y, yaw, z, two driven wheels and a frictionless caster ball."""
    caster_z, inertia = _CASTER_RADIUS - _ROBOT_Z, f"{_YAW_INERTIA} {_YAW_INERTIA} {_YAW_INERTIA}"
    robot = f"""
    <body name="robot" pos="0 0 {_ROBOT_Z}">
      {_PLANAR_JOINTS}
      <joint name="z" type="slide" axis="0 0 1"/>
      <inertial pos="0 0 0" mass="{_MASS - 2 * _WHEEL_MASS:.6g}" diaginertia="{inertia}"/>
      <geom name="robot" class="robot" type="sphere" size="{DiffDriveNav.robot_radius}"/>{_CHASSIS_VISUALS}
      {_wheel("left", TRACK / 2)}{_wheel("right", -TRACK / 2)}
      <body name="caster" pos="{_CASTER_X} 0 {caster_z:.6g}">
        <geom type="sphere" size="{_CASTER_RADIUS}" mass="0" contype="2" conaffinity="0" condim="1" priority="1"
              group="2" rgba=".5 .5 .5 1"/>
      </body>
    </body>"""
    xml = model_xml("diffdrive_nav", WHEELED_TIMESTEP, robot, _obstacles_xml(empty), floor_half_extent=3.0,
                    overview_height=5.0, floor_contact=True)
    return with_actuators(xml, f"{_wheel_actuator('left')}\n{_wheel_actuator('right')}")


def build_environment(
    *,
    max_acceleration: float | None = MAX_ACCELERATION,
    max_turn_acceleration: float | None = MAX_TURN_ACCELERATION,
    robot: str = "kinematic",
    **options,
) -> control.Environment:
    """The dm_control environment of ``diffdrive_nav``.

    Args:
        max_acceleration: forward acceleration limit of the speed servo (m/s^2); ``None``
            removes it.
        max_turn_acceleration: yaw acceleration limit of the turn servo (rad/s^2); ``None``
            removes it.
        robot: ``"kinematic"`` (chassis velocity servos) or ``"wheeled"`` (driven wheels with
            contact friction and their own ramped controller; the two limits above are for the
            kinematic robot only).
        **options: those of :func:`envs._task.task_environment`: ``empty``, ``layout``, ``seed``,
            ``episode_steps`` (default 300) and ``terminate_on_collision``.

    Returns:
        A ``dm_control.rl.control.Environment``.

    Raises:
        ValueError: an unknown ``robot``, or acceleration limits other than the defaults for the
            wheeled robot.

    Examples:
        >>> env = build_environment(layout=0)
        >>> int(env.reset().observation["obstacles_mask"].sum())
        12
    """
    if robot not in ROBOTS:
        raise ValueError(f"unknown robot {robot!r} for diffdrive_nav; choose one of {ROBOTS}")
    if robot == "kinematic":
        return task_environment(DiffDriveNav, _model, max_acceleration=max_acceleration,
                                max_turn_acceleration=max_turn_acceleration, **options)
    if (max_acceleration, max_turn_acceleration) != (MAX_ACCELERATION, MAX_TURN_ACCELERATION):
        raise ValueError("max_acceleration and max_turn_acceleration apply to robot='kinematic' only; the wheeled "
                         f"robot ramps its wheels at {WHEEL_ACCELERATION} rad/s^2")
    return task_environment(WheeledDiffDriveNav, _wheeled_model, **options)
