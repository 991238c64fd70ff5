"""``hexarotor_wind``: a velocity-commanded hexarotor in wind passing 10 checkpoints in order.

* Robot: the multirotor of :mod:`envs._aerial` with mass 2 kg and a collision
  sphere of radius 0.4 m; action = commanded velocity ``[-5, 5]^3`` m/s at 10 Hz.
* Wind: constant horizontal wind per episode, speed ``U[0, 3]`` m/s in a uniformly
  random direction, acting as the drag force ``0.5 kg/s * (wind - velocity)`` written
  to ``xfrc_applied`` before every control step (also in the empty variant: offline
  data is collected under wind). The wind is not observed.
* Flight controller: the velocity loop has integral action, as a real one (PX4,
  AirSim) has. The servo tracks ``command + offset``, and after every control step
  ``offset += 0.5 * (command - velocity)`` on every axis whose servo force is below
  its limit (anti-windup; uncapped servos always integrate). In constant wind the zero command
  therefore stops the robot *and keeps it stopped* (paper Assumption 1); a pure
  velocity servo would let it drift downwind forever. The offset is part of the
  state (it is the controller's memory) and starts at 0.
* State ``(x, y, z, vx, vy, vz, ox, oy, oz)`` (position, velocity, integral
  offset); process noise ``U[-0.02, 0.02]`` m/s per velocity, added after the
  offset update.
* Checkpoints: 10 spheres of radius 1 m, equally spaced on the horizontal circle of
  radius 6 m at height 2.5 m, visited counter-clockwise from ``(6, 0, 2.5)``; the
  robot starts hovering at ``(0, 0, 2.5)``. Obstacles (4 pillars, 4 boxes) are placed
  at random 1.8-3.5 m inside or outside the ring but clear of the straight legs
  between consecutive checkpoints, so the high-reward path runs next to them.
  ``K = 14`` obstacles (6 boundary slabs first), ``p = 7`` generators.
* Observation (26): 16 lidar ranges / 10 m, offset to the current checkpoint (3),
  offset from the current to the next checkpoint (3; zero at the last one),
  velocity (3), fraction of checkpoints passed.
* Reward: progress towards the current checkpoint + 10 per checkpoint - 10 on a
  collision. Ends after the 10th checkpoint or a collision (``terminated``) or
  after 400 steps (``truncated``).
"""
from __future__ import annotations

import dataclasses

import numpy as np
from dm_control.rl import control

from envs._aerial import ARENA, MAX_ACCELERATION, N_BOUNDARY, AerialTask, boundary, draw_obstacle
from envs._obstacles import KeepOut, Layout, Obstacle, place_obstacles
from envs._task import task_environment

N_CHECKPOINTS = 10
CHECKPOINT_RADIUS = 1.0
RING_RADIUS = 6.0
RING_HEIGHT = 2.5
MAX_WIND = 3.0
DRAG = 0.5
INTEGRAL_GAIN = 0.5
_N_PILLARS = 4
_N_BOXES = 4


def _draw_near_ring(rng: np.random.RandomState, kind: str) -> Obstacle:
    """A random obstacle 1.8-3.5 m inside or outside the checkpoint ring."""
    obstacle = draw_obstacle(rng, kind)
    angle = rng.uniform(0, 2 * np.pi)
    radius = RING_RADIUS + rng.choice([-1.0, 1.0]) * rng.uniform(1.8, 3.5)
    position = np.array([radius * np.cos(angle), radius * np.sin(angle), obstacle.pos[2]])
    return dataclasses.replace(obstacle, pos=position)


def checkpoints() -> np.ndarray:
    """The 10 checkpoint centres ``[10, 3]`` in visiting order."""
    angles = np.arange(N_CHECKPOINTS) * 2 * np.pi / N_CHECKPOINTS
    height = np.full(N_CHECKPOINTS, RING_HEIGHT)
    return np.stack([RING_RADIUS * np.cos(angles), RING_RADIUS * np.sin(angles), height], axis=1)


class HexarotorWind(AerialTask):
    """The dm_control task of ``hexarotor_wind`` (see the module docstring).

    Attributes:
        wind: the current episode's wind velocity ``[3]`` (m/s).
        offset: the flight controller's integral offset ``[3]`` (m/s), added to the command.

    Examples:
        >>> env = build_environment(seed=0)
        >>> env.reset().observation["observation"].shape
        (26,)
    """

    name = "hexarotor_wind"
    layout_code = 4
    capacity = N_BOUNDARY + _N_PILLARS + _N_BOXES
    robot_radius = 0.4
    observation_dim = 16 + 3 + 3 + 3 + 1
    obstacle_kinds = ("box",) * N_BOUNDARY + ("cylinder",) * _N_PILLARS + ("box",) * _N_BOXES
    start = np.array([0.0, 0.0, RING_HEIGHT])
    noise_center = np.zeros(9)
    noise_generators = np.concatenate([AerialTask.noise_generators, np.zeros((3, 3))])
    episode_steps = 400
    n_pillars = _N_PILLARS
    n_boxes = _N_BOXES
    mass = 2.0
    n_rotors = 6

    def _new_layout(self, rng):
        goals = checkpoints()
        speed, direction = rng.uniform(0.0, MAX_WIND), rng.uniform(0, 2 * np.pi)
        self.wind = np.array([speed * np.cos(direction), speed * np.sin(direction), 0.0])
        obstacles = []
        if not self.empty:
            legs = [self.start, *goals]
            clearance = self.robot_radius + 0.6
            keep_out = [KeepOut(a, b, clearance) for a, b in zip(legs[:-1], legs[1:])]
            keep_out += [KeepOut(goal, clearance=CHECKPOINT_RADIUS + self.robot_radius + 0.3) for goal in goals]
            obstacles = boundary() + place_obstacles(rng, _draw_near_ring, self.obstacle_kinds[N_BOUNDARY:], keep_out)
        center, generators, mask = self._layout_zonotopes(obstacles)
        half = ARENA + 0.5
        return Layout(
            obstacles=tuple(obstacles),
            obstacle_center=center,
            obstacle_generators=generators,
            obstacle_mask=mask,
            goals=goals,
            goal_radius=CHECKPOINT_RADIUS,
            start=self.start.copy(),
            extent=(-half, half, -half, half),
        )

    def _reset_robot(self, physics, rng) -> None:
        super()._reset_robot(physics, rng)
        self.offset = np.zeros(3)

    def _apply_action(self, action, physics) -> None:
        self._command = action
        physics.data.ctrl[:] = action + self.offset
        physics.data.xfrc_applied[self._body, :3] = DRAG * (self.wind - physics.data.qvel[:3])

    def _bind(self, physics) -> None:
        super()._bind(physics)
        model = physics.model
        self._force_limit = np.where(model.actuator_forcelimited, model.actuator_forcerange[:, 1], np.inf)

    def after_step(self, physics):  # the controller measures the velocity before the process noise
        integrating = np.abs(physics.data.actuator_force) < self._force_limit  # anti-windup: not while saturated
        self.offset = self.offset + integrating * INTEGRAL_GAIN * (self._command - physics.data.qvel[:3])
        super().after_step(physics)

    def state(self, physics):
        return np.concatenate([super().state(physics), self.offset])

    def _policy_observation(self, physics):
        goals = self.layout.goals
        index = min(self.goal_index, N_CHECKPOINTS - 1)
        following = goals[index + 1] - goals[index] if index + 1 < N_CHECKPOINTS else np.zeros(3)
        position = physics.data.qpos[:3]
        return np.concatenate(
            [
                self._lidar_scan(physics),
                goals[index] - position,
                following,
                physics.data.qvel[:3],
                [self.goal_index / N_CHECKPOINTS],
            ]
        )


def build_environment(*, max_acceleration: float | None = MAX_ACCELERATION, **options) -> control.Environment:
    """The dm_control environment of ``hexarotor_wind``.

    Args:
        max_acceleration: force limit of the velocity servos per unit mass (m/s^2).
            ``None`` removes it: the servos are then linear (see :mod:`envs._aerial`),
            and the zero command still stops the robot within ``n_brk`` steps.
        **options: those of :func:`envs._task.task_environment`: ``empty`` (the wind stays), ``layout``
            (fixes the obstacles and the wind), ``seed``, ``episode_steps`` (default 400) and
            ``terminate_on_collision``.

    Returns:
        A ``dm_control.rl.control.Environment``.

    Examples:
        >>> env = build_environment(layout=3)
        >>> env.reset().observation["obstacles_center"].shape
        (14, 3)
    """
    return task_environment(HexarotorWind, HexarotorWind.model, max_acceleration=max_acceleration, **options)
