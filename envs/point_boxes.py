"""``point_boxes``: a velocity-commanded point mass among boxes crowded around its start.

A small, fast task on which a uniformly random policy collides in most episodes,
so that a safety layer has something to prevent.

* Robot: a sphere of radius 0.1 m (mass 1 kg) on two slide joints (x, y). The action
  is the commanded velocity ``(v_x, v_y) ∈ [-1, 1]^2`` m/s, held for 0.1 s and tracked
  at every 0.02 s physics step by one MuJoCo velocity servo per axis (time constant
  50 ms, force saturated at 5 N, i.e. an acceleration limit of 5 m/s^2 per axis), as
  the multirotors of :mod:`envs._aerial`. The zero command stops the robot from any
  velocity of the data region within 3 steps. ``max_acceleration=None`` (an argument
  of :func:`build_environment` and :func:`envs.make`) removes the force limit: the
  servos, and a whole control step away from contacts, are then linear, so that a
  linear model fitted to offline data is exact up to the noise.
* State ``(x, y, vx, vy)``; process noise ``U[-0.01, 0.01]`` m/s on each velocity,
  added to the simulation after every step.
* Observation (12): the state, then 8 world-aligned lidar ranges (every 45° from +x,
  counter-clockwise) divided by the 2 m range.
* Layout: a 3 m × 3 m arena (four walls, inner faces at ``|x|, |y| = 1.5``) holding
  4-6 random axis-aligned boxes (half sides 0.1-0.25 m) spread around the start at
  the centre, one per equal angular sector, each with its circumscribed disc
  0.35-0.65 m from the start, so the robot starts at rest at least 0.25 m clear of
  everything. ``K = 10`` obstacles (the 4 walls
  first, unused box slots masked), ``p = 6`` generators.
* Reward: the speed ``‖(vx, vy)‖`` after the step, or -10 on a collision. There is
  no goal (``goal_reached`` stays False).
* Ends on a collision (``terminated``) or after 80 steps (``truncated``).
* Empty variant: no walls or boxes, random start velocity in ``[-1, 1]^2``, truncated
  when ``|x|`` or ``|y|`` exceeds 3 m.
"""
from __future__ import annotations

import numpy as np
from dm_control.rl import control

from envs._lidar import Lidar, rings
from envs._mjcf import model_xml, with_actuators
from envs._obstacles import Layout, Obstacle, boundary_walls, obstacle_bodies_xml
from envs._task import SafetyTask, task_environment

ARENA = 1.5
MAX_SPEED = 1.0
MAX_ACCELERATION = 5.0
NOISE = 0.01
DATA_REGION = 3.0
LIDAR_RANGE = 2.0
N_LIDAR = 8
COLLISION_PENALTY = 10.0
#: fewest / most random boxes per layout
N_BOXES = (4, 6)
#: distance from the start to a box's footprint (its circumscribed disc)
START_CLEARANCE = (0.35, 0.65)
_BOX_HALF_SIDE = (0.1, 0.25)
_HEIGHT = 0.4
_ROBOT_Z = 0.1
_WALL_THICKNESS = 0.2
_SERVO_TIME_CONSTANT = 0.05
_MASS = 1.0


def _walls() -> list[Obstacle]:
    return boundary_walls(ARENA, _WALL_THICKNESS, _HEIGHT, _HEIGHT / 2)


def draw_boxes(rng: np.random.RandomState, start: np.ndarray) -> list[Obstacle]:
    """4-6 axis-aligned boxes around ``start [2]``, one per equal angular sector.

    Box ``i`` sits at a random angle in the middle half of sector ``i`` (the sectors
    are rotated at random), with its footprint disc ``START_CLEARANCE`` away from
    ``start``.

    Examples:
        >>> boxes = draw_boxes(np.random.RandomState(0), np.zeros(2))
        >>> 4 <= len(boxes) <= 6, all(np.linalg.norm(b.pos[:2]) >= b.xy_radius + 0.35 for b in boxes)
        (True, True)
    """
    n = rng.randint(N_BOXES[0], N_BOXES[1] + 1)
    sector = 2 * np.pi / n
    offset = rng.uniform(0, 2 * np.pi)
    boxes = []
    for i in range(n):
        angle = offset + sector * (i + rng.uniform(-0.25, 0.25))
        half = rng.uniform(*_BOX_HALF_SIDE, 2)
        distance = np.hypot(*half) + rng.uniform(*START_CLEARANCE)
        centre = start + distance * np.array([np.cos(angle), np.sin(angle)])
        boxes.append(Obstacle("box", np.array([*centre, _HEIGHT / 2]), np.array([*half, _HEIGHT / 2])))
    return boxes


class PointBoxes(SafetyTask):
    """The dm_control task of ``point_boxes`` (see the module docstring).

    Examples:
        >>> env = build_environment(seed=0)
        >>> env.reset().observation["obstacles_center"].shape
        (10, 2)
    """

    name = "point_boxes"
    layout_code = 5
    obstacle_dim = 2
    capacity = 4 + N_BOXES[1]
    robot_radius = 0.1
    observation_dim = 4 + N_LIDAR
    action_low = np.full(2, -MAX_SPEED)
    action_high = np.full(2, MAX_SPEED)
    noise_center = np.zeros(4)
    noise_generators = np.array([[0.0, 0.0], [0.0, 0.0], [NOISE, 0.0], [0.0, NOISE]])
    position_dims = (0, 1)
    velocity_dims = (2, 3)
    obstacle_kinds = ("box",) * (4 + N_BOXES[1])
    episode_steps = 80
    # Braking from ``|v| = 1.01`` m/s per axis: 0.15 s at the 5 m/s^2 limit, then the servo removes 40 % of
    # the rest per 0.02 s physics step, leaving ≤ 0.006 m/s after 3 steps, plus ≤ 0.01 m/s of noise from the
    # last step and ≤ 0.001 m/s from the one before (tested against the stop tolerance).
    n_brk = 3
    n_plan = 6
    braking_action = np.zeros(2)
    stop_tolerance = 0.05

    def _bind(self, physics) -> None:
        self._lidar = Lidar(rings(N_LIDAR, np.zeros(1)), LIDAR_RANGE, physics.model.name2id("robot", "body"))
        self._origin = np.array([0.0, 0.0, _ROBOT_Z])

    def _new_layout(self, rng):
        start = np.zeros(2)
        obstacles = [] if self.empty else _walls() + draw_boxes(rng, start)
        center, generators, mask = self._layout_zonotopes(obstacles)
        half = ARENA + _WALL_THICKNESS
        return Layout(
            obstacles=tuple(obstacles),
            obstacle_center=center,
            obstacle_generators=generators,
            obstacle_mask=mask,
            goals=np.zeros((0, 2)),
            goal_radius=0.0,
            start=start,
            extent=(-half, half, -half, half),
        )

    def _reset_robot(self, physics, rng) -> None:
        physics.data.qpos[:] = self.layout.start
        if self.empty:
            physics.data.qvel[:] = self.random.uniform(-MAX_SPEED, MAX_SPEED, 2)

    def _apply_action(self, action, physics) -> None:
        physics.data.ctrl[:] = action

    def _add_state_noise(self, physics, noise) -> None:
        physics.data.qvel[:] += noise[2:]

    def state(self, physics):
        return np.concatenate([physics.data.qpos, physics.data.qvel])

    def _policy_observation(self, physics):
        self._origin[:2] = physics.data.qpos
        ranges = self._lidar.scan(physics, self._origin)
        return np.concatenate([physics.data.qpos, physics.data.qvel, ranges / LIDAR_RANGE])

    def _speed(self, physics) -> float:
        vx, vy = physics.data.qvel
        return float(np.hypot(vx, vy))

    def get_reward(self, physics) -> float:
        return -COLLISION_PENALTY if self._collision else self._speed(physics)

    def _in_data_region(self, physics) -> bool:
        return bool(np.all(np.abs(physics.data.qpos) <= DATA_REGION))


def _model(empty: bool, max_acceleration: float | None) -> str:
    rho = PointBoxes.robot_radius
    robot = f"""
    <body name="robot" pos="0 0 {_ROBOT_Z}">
      <joint name="x" type="slide" axis="1 0 0"/>
      <joint name="y" type="slide" axis="0 1 0"/>
      <geom name="robot" class="robot" type="sphere" size="{rho}" mass="{_MASS}"/>
      <geom class="visual" type="sphere" size="{0.5 * rho:.4g}" rgba=".9 .35 .2 1"/>
      <camera name="follow" mode="trackcom" pos="0 -1.5 2" xyaxes="1 0 0 0 0.8 0.6"/>
    </body>"""
    max_half = [w.half_size for w in _walls()]
    max_half += [[_BOX_HALF_SIDE[1], _BOX_HALF_SIDE[1], _HEIGHT / 2]] * N_BOXES[1]
    obstacles = "" if empty else obstacle_bodies_xml(PointBoxes.obstacle_kinds, max_half)
    xml = model_xml("point_boxes", 0.02, robot, obstacles, floor_half_extent=DATA_REGION, overview_height=3.4)
    kv = _MASS / _SERVO_TIME_CONSTANT
    if max_acceleration is None:
        limit = 'forcelimited="false"'
    else:
        force = _MASS * max_acceleration
        limit = f'forcelimited="true" forcerange="{-force:.6g} {force:.6g}"'
    actuators = "\n".join(f'    <velocity name="v{axis}" joint="{axis}" kv="{kv:.6g}" {limit}/>' for axis in ("x", "y"))
    return with_actuators(xml, actuators)


def build_environment(*, max_acceleration: float | None = MAX_ACCELERATION, **options) -> control.Environment:
    """The dm_control environment of ``point_boxes``.

    Args:
        max_acceleration: force limit of the servos per unit mass (m/s^2). ``None``
            removes it: the servos are then linear, and so is a whole control step
            away from contacts, ``(vx, vy)+ = a (vx, vy) + (1 - a) u`` with
            ``a = 0.6^5 ≈ 0.078`` (explicit Euler), plus the noise. The zero command
            still stops the robot within ``n_brk`` steps.
        **options: those of :func:`envs._task.task_environment`: ``empty``, ``layout`` (fixes the
            boxes), ``seed``, ``episode_steps`` (default 80) and ``terminate_on_collision``.

    Returns:
        A ``dm_control.rl.control.Environment``.

    Examples:
        >>> env = build_environment(empty=True, seed=0)
        >>> bool(env.reset().observation["obstacles_mask"].any())
        False
    """
    return task_environment(PointBoxes, _model, max_acceleration=max_acceleration, **options)
