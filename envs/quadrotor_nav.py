"""``quadrotor_nav``: a velocity-commanded quadrotor navigating to a goal in 3-D.

* Robot: the multirotor of :mod:`envs._aerial` with mass 1 kg and a collision
  sphere of radius 0.3 m; action = commanded velocity ``[-5, 5]^3`` m/s at 10 Hz.
* State ``(x, y, z, vx, vy, vz)``; process noise ``U[-0.02, 0.02]`` m/s per velocity.
* Observation (22): 16 lidar ranges (2 rings of 8 at ±25° elevation, i.e. a 50°
  vertical and 360° horizontal field of view, world-aligned) divided by the 10 m
  range, goal offset ``goal - position`` (3), velocity (3).
* Layout: the arena of :mod:`envs._aerial` with 6 random pillars and 6 random
  boxes; start hovering at ``(0, 0, 2)``; a goal sphere of radius 0.75 m, 5-8.5 m
  away horizontally at height 1-5 m. ``K = 18`` obstacles (6 boundary slabs
  first), ``p = 7`` generators.
* Ends at the goal or a collision (``terminated``) or after 200 steps (``truncated``).
* Empty variant: no obstacles (not even the floor), random start velocity, truncated
  outside ``|x|, |y| ≤ 10, -4 ≤ z ≤ 8``.
* Rotor robot (``robot="rotor"``): the same task with a 1 kg free body lifted and steered by four
  rotors and flown by an onboard cascaded velocity controller (:mod:`envs._rotor`); same spaces, state,
  noise and layouts, ``n_brk = 16``.
"""
from __future__ import annotations

import numpy as np
from dm_control.rl import control

from envs._aerial import ARENA, MAX_ACCELERATION, N_BOUNDARY, AerialTask, boundary, draw_obstacle
from envs._obstacles import KeepOut, Layout, place_obstacles
from envs._rotor import QUADROTOR, RotorTask, aerial_environment

GOAL_RADIUS = 0.75
_N_PILLARS = 6
_N_BOXES = 6


class QuadrotorNav(AerialTask):
    """The dm_control task of ``quadrotor_nav`` (see the module docstring).

    Examples:
        >>> env = build_environment(seed=0)
        >>> env.reset().observation["obstacles_generators"].shape
        (18, 3, 7)
    """

    name = "quadrotor_nav"
    layout_code = 3
    capacity = N_BOUNDARY + _N_PILLARS + _N_BOXES
    robot_radius = 0.3
    observation_dim = 16 + 3 + 3
    obstacle_kinds = ("box",) * N_BOUNDARY + ("cylinder",) * _N_PILLARS + ("box",) * _N_BOXES
    episode_steps = 200
    n_pillars = _N_PILLARS
    n_boxes = _N_BOXES
    mass = 1.0
    n_rotors = 4

    def _new_layout(self, rng):
        angle, distance = rng.uniform(0, 2 * np.pi), rng.uniform(5.0, 8.5)
        goal = np.array([distance * np.cos(angle), distance * np.sin(angle), rng.uniform(1.0, 5.0)])
        obstacles = []
        if not self.empty:
            keep_out = [
                KeepOut(self.start, clearance=self.robot_radius + 1.0),
                KeepOut(goal, clearance=GOAL_RADIUS + self.robot_radius + 0.3),
            ]
            obstacles = boundary() + place_obstacles(rng, draw_obstacle, self.obstacle_kinds[N_BOUNDARY:], keep_out)
        center, generators, mask = self._layout_zonotopes(obstacles)
        half = ARENA + 0.5
        return Layout(
            obstacles=tuple(obstacles),
            obstacle_center=center,
            obstacle_generators=generators,
            obstacle_mask=mask,
            goals=goal[None],
            goal_radius=GOAL_RADIUS,
            start=self.start.copy(),
            extent=(-half, half, -half, half),
        )

    def _policy_observation(self, physics):
        return np.concatenate(
            [self._lidar_scan(physics), self.current_goal() - physics.data.qpos[:3], physics.data.qvel[:3]]
        )


class RotorQuadrotorNav(RotorTask, QuadrotorNav):
    """``quadrotor_nav`` with the rotor-driven quadrotor (``robot="rotor"``, see :mod:`envs._rotor`).

    1 kg, four rotors of 4.9 N at most on 0.24 m arms, flown by the onboard cascaded velocity controller
    (no integral action: there is no wind, and the hover thrust is known). Same spaces, state, noise and
    layouts as the kinematic quadrotor; it brakes more slowly (the body must tilt before it decelerates, and
    its thrust is limited), so its ``n_brk`` is 16 (``envs.safety_info("quadrotor_nav", robot="rotor")``).

    Examples:
        >>> env = build_environment(robot="rotor", seed=0)
        >>> env.reset().observation["state"].shape, env.physics.model.nu
        ((6,), 4)
    """

    airframe = QUADROTOR
    # measured (zero command after random commands held 1-36 steps, noise on): stopped within 15 steps from all of
    # 400 reachable states, median 8; the slowest brake a climbing diagonal (the tilt is taken against g)
    n_brk = 16
    n_plan = 17


#: the task class of each robot (``robot`` of :func:`build_environment`)
ROBOT_TASKS = {"kinematic": QuadrotorNav, "rotor": RotorQuadrotorNav}
ROBOTS = tuple(ROBOT_TASKS)


def build_environment(
    *, max_acceleration: float | None = MAX_ACCELERATION, robot: str = "kinematic", **options
) -> control.Environment:
    """The dm_control environment of ``quadrotor_nav``.

    Args:
        max_acceleration: force limit of the velocity servos per unit mass (m/s^2).
            ``None`` removes it: the servos are then linear (see :mod:`envs._aerial`),
            and the zero command still stops the robot within ``n_brk`` steps.
        robot: ``"kinematic"`` (level body, velocity servos) or ``"rotor"`` (four rotors and an onboard
            cascaded controller, :mod:`envs._rotor`; ``max_acceleration`` is for the kinematic robot only).
        **options: those of :func:`envs._task.task_environment`: ``empty``, ``layout``, ``seed``,
            ``episode_steps`` (default 200) and ``terminate_on_collision``.

    Returns:
        A ``dm_control.rl.control.Environment``.

    Raises:
        ValueError: an unknown ``robot``, or an acceleration limit other than the default for the rotor robot.

    Examples:
        >>> env = build_environment(empty=True, seed=0)
        >>> bool(env.reset().observation["obstacles_mask"].any())
        False
    """
    return aerial_environment(ROBOT_TASKS, robot, max_acceleration, **options)
