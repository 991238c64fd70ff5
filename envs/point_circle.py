"""``point_circle``: a 2-D double integrator following a circle it may not reach.

After Achiam et al. (2017) and Wagener et al. (2021), as in Sec. IV of the BRSL paper.

* Robot: a sphere of radius 0.05 m on two slide joints (x, y), driven by force motors.
  The action is the acceleration ``(a_x, a_y) ∈ [-1, 1]^2`` m/s^2; before each step
  the task scales it so that the speed after the step stays ≤ 2 m/s (saturation).
  Physics: 2 substeps of 0.05 s per 0.1 s control step.
* State ``(x, y, ẋ, ẏ)``; process noise ``U[-0.01, 0.01]`` m/s on each velocity,
  added to the simulation after every step.
* Safe set ``|x| ≤ 1.2, |y| ≤ 1.2``; four wall boxes just outside it are the
  obstacles (the robot sphere touches a wall exactly when its centre leaves the
  box), target circle radius ``r = 2.0`` (``‖(1.2, 1.2)‖ ≈ 1.70 < r``).
* Reward ``((ẋ, ẏ)·(-y, x)) / (1 + |‖(x, y)‖ - r|)``.
* Observation ``(x, y, ẋ, ẏ, ‖(x, y)‖ - r)``. Episodes last 200 steps; leaving the
  safe set (touching a wall) ends the episode (``terminated``), as in the point
  environment of Wagener et al. (2021) that the paper follows, unless
  ``terminate_on_collision=False``. There is no goal (``goal_reached`` stays False).
* Empty variant: no walls, random start velocity (speed ≤ 2), truncated when
  ``|x|`` or ``|y|`` exceeds 5 m.
"""
from __future__ import annotations

import numpy as np
from dm_control.rl import control

from envs._mjcf import model_xml, with_actuators
from envs._obstacles import Layout, boundary_walls, obstacle_bodies_xml
from envs._task import SafetyTask, task_environment

PATH_RADIUS = 2.0
X_MAX = 1.2
Y_MAX = 1.2
MAX_SPEED = 2.0
MAX_ACCELERATION = 1.0
DATA_REGION = 5.0
_WALL_THICKNESS = 0.5
_ROBOT_HEIGHT = 0.1


class PointCircle(SafetyTask):
    """The dm_control task of ``point_circle`` (see the module docstring).

    Examples:
        >>> env = build_environment(seed=0)
        >>> env.reset().observation["state"].shape
        (4,)
    """

    name = "point_circle"
    layout_code = 1
    obstacle_dim = 2
    capacity = 4
    robot_radius = 0.05
    observation_dim = 5
    action_low = np.full(2, -MAX_ACCELERATION)
    action_high = np.full(2, MAX_ACCELERATION)
    noise_center = np.zeros(4)
    noise_generators = np.array([[0.0, 0.0], [0.0, 0.0], [0.01, 0.0], [0.0, 0.01]])
    position_dims = (0, 1)
    velocity_dims = (2, 3)
    obstacle_kinds = ("box",) * 4
    episode_steps = 200
    n_brk = 23
    n_plan = 25
    braking_action = np.zeros(2)
    stop_tolerance = 0.02

    @classmethod
    def braking_policy(cls, state):
        """``a = clip(-v / dt, -1, 1)`` per axis.

        Worst case with noise: while saturated each step removes at least
        ``0.1 - 0.01`` m/s, so from ``|v_i| ≤ 2.01`` the speed is below 0.1 m/s after 22
        steps and within the noise (``≤ 0.01`` m/s per axis) after the 23rd: ``n_brk = 23``.

        Args:
            state: ``[..., 4]`` states ``(x, y, ẋ, ẏ)``.

        Returns:
            Accelerations ``[..., 2]``.
        """
        return (-state[..., 2:4] / cls.dt).clamp(-MAX_ACCELERATION, MAX_ACCELERATION)

    def _bind(self, physics) -> None:
        self._mass = float(physics.model.body_subtreemass[physics.model.name2id("robot", "body")])

    def _new_layout(self, rng):
        walls = [] if self.empty else boundary_walls(X_MAX + self.robot_radius, _WALL_THICKNESS, 0.4, _ROBOT_HEIGHT)
        center, generators, mask = self._layout_zonotopes(walls)
        half = PATH_RADIUS + 0.3
        return Layout(
            obstacles=tuple(walls),
            obstacle_center=center,
            obstacle_generators=generators,
            obstacle_mask=mask,
            goals=np.zeros((0, 2)),
            goal_radius=0.0,
            start=rng.uniform(-0.5, 0.5, 2) * np.array([X_MAX, Y_MAX]),
            extent=(-half, half, -half, half),
            path_radius=PATH_RADIUS,
        )

    def _reset_robot(self, physics, rng) -> None:
        physics.data.qpos[:2] = self.layout.start
        if self.empty:
            angle, speed = self.random.uniform(0, 2 * np.pi), MAX_SPEED * np.sqrt(self.random.uniform())
            physics.data.qvel[:2] = speed * np.array([np.cos(angle), np.sin(angle)])

    def _apply_action(self, action, physics) -> None:
        velocity = physics.data.qvel[:2]
        target = velocity + action * self.dt
        speed = np.linalg.norm(target)
        if speed > MAX_SPEED:
            action = (target * (MAX_SPEED / speed) - velocity) / self.dt
        physics.data.ctrl[:] = self._mass * action

    def _add_state_noise(self, physics, noise) -> None:
        physics.data.qvel[:2] += noise[2:]

    def state(self, physics):
        return np.concatenate([physics.data.qpos[:2], physics.data.qvel[:2]])

    def _policy_observation(self, physics):
        position = physics.data.qpos[:2]
        return np.concatenate([position, physics.data.qvel[:2], [np.linalg.norm(position) - PATH_RADIUS]])

    def _speed(self, physics) -> float:
        return float(np.linalg.norm(physics.data.qvel[:2]))

    def get_reward(self, physics) -> float:
        x, y = physics.data.qpos[:2]
        vx, vy = physics.data.qvel[:2]
        return float((-vx * y + vy * x) / (1.0 + abs(np.hypot(x, y) - PATH_RADIUS)))

    def _in_data_region(self, physics) -> bool:
        return bool(np.all(np.abs(physics.data.qpos[:2]) <= DATA_REGION))


def _model(empty: bool) -> str:
    robot = f"""
    <body name="robot" pos="0 0 {_ROBOT_HEIGHT}">
      <joint name="x" type="slide" axis="1 0 0"/>
      <joint name="y" type="slide" axis="0 1 0"/>
      <geom name="robot" class="robot" type="sphere" size="{PointCircle.robot_radius}" mass="1" rgba=".2 .5 .9 1"/>
      <camera name="follow" mode="trackcom" pos="0 -1.5 2" xyaxes="1 0 0 0 0.8 0.6"/>
    </body>
    <geom name="path" class="visual" type="cylinder" size="{PATH_RADIUS} 0.001" pos="0 0 0.001" rgba=".3 .7 .3 .25"/>"""
    walls = boundary_walls(X_MAX + PointCircle.robot_radius, _WALL_THICKNESS, 0.4, _ROBOT_HEIGHT)
    obstacles = "" if empty else obstacle_bodies_xml(PointCircle.obstacle_kinds, [w.half_size for w in walls])
    xml = model_xml("point_circle", 0.05, robot, obstacles, floor_half_extent=6.0, overview_height=4.5)
    return with_actuators(
        xml, '    <motor name="x" joint="x" ctrllimited="false"/>\n    <motor name="y" joint="y" ctrllimited="false"/>'
    )


def build_environment(**options) -> control.Environment:
    """The dm_control environment of ``point_circle``.

    Args:
        **options: those of :func:`envs._task.task_environment`: ``empty``, ``layout`` (sets the start
            position), ``seed``, ``episode_steps`` (default 200) and ``terminate_on_collision`` (True:
            the episode ends when the robot touches a wall, i.e. leaves the safe set; False: it goes
            on, the robot may cross the walls).

    Returns:
        A ``dm_control.rl.control.Environment``.

    Examples:
        >>> env = build_environment(seed=0, empty=True)
        >>> env.step(np.array([1.0, 0.0])).step_type.name
        'FIRST'
    """
    return task_environment(PointCircle, _model, **options)
