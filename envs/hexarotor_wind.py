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
* Rotor robot (``robot="rotor"``): the same task with a 2 kg free body lifted and steered by six
  rotors and flown by an onboard cascaded velocity controller (:mod:`envs._rotor`) that feeds its drag
  forward and learns the wind while hovering; same spaces, state, noise, layouts and wind, ``n_brk = 16``.
"""
from __future__ import annotations

import dataclasses

import numpy as np
from dm_control.rl import control

from envs import _rotor
from envs._aerial import ARENA, MAX_ACCELERATION, N_BOUNDARY, AerialTask, boundary, draw_obstacle
from envs._obstacles import KeepOut, Layout, Obstacle, place_obstacles
from envs._rotor import HEXAROTOR, RotorTask, aerial_environment

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


class RotorHexarotorWind(RotorTask, HexarotorWind):
    """``hexarotor_wind`` with the rotor-driven hexarotor (``robot="rotor"``, see :mod:`envs._rotor`).

    2 kg, six rotors of 6.5 N at most on 0.32 m arms, flown by the onboard cascaded velocity controller. The
    wind drag ``DRAG * (wind - velocity)`` is rewritten to ``xfrc_applied`` before every 5 ms physics step.
    The controller knows its own drag coefficient (as it knows its mass) and feeds the drag of its ground
    velocity forward (``DRAG v / m`` added to the acceleration demand), which leaves only the wind's push,
    constant in an episode, to its integral offset. That offset is the task's ``offset`` (state dims 6-8, m/s,
    as for the kinematic robot): it integrates ``INTEGRAL_GAIN (command - velocity)`` (5 /s) at every physics
    step, but only while hovering (command within 0.05 m/s of zero and velocity error within 0.15 m/s on every
    axis; not on an axis whose demand is clipped), as PX4 holds position when the sticks are released. So
    flying does not wind it up, and in constant wind the zero command stops the robot and keeps it stopped
    (paper Assumption 1); offset and tracking are exact once it has hovered. Same spaces, state, noise,
    layouts and wind as the kinematic hexarotor; it brakes more slowly, so its ``n_brk`` is 16
    (``envs.safety_info("hexarotor_wind", robot="rotor")``).

    Examples:
        >>> env = build_environment(robot="rotor", seed=0)
        >>> env.reset().observation["state"].shape, env.physics.model.nu
        ((9,), 6)
    """

    airframe = HEXAROTOR
    integral_gain = _rotor.INTEGRAL_GAIN
    drag_feedforward = DRAG
    # measured as for the rotor quadrotor: stopped within 15 steps from all of 400 reachable states, median 8
    n_brk = 16
    n_plan = 17

    @property
    def offset(self) -> np.ndarray:
        """The controller's integral offset ``[3]`` (m/s)."""
        return np.array(self._controller.offset)

    @offset.setter
    def offset(self, value) -> None:
        self._controller.offset = [float(v) for v in value]

    def _reset_robot(self, physics, rng) -> None:
        super()._reset_robot(physics, rng)
        self._wind = [float(w) for w in self.wind[:2]]

    def _onboard(self) -> None:
        data = self._controller.data
        vx, vy, vz = data.qvel[:3].tolist()
        data.xfrc_applied[self._body, :3] = [DRAG * (self._wind[0] - vx), DRAG * (self._wind[1] - vy), -DRAG * vz]
        self._controller.update()

    def after_step(self, physics):  # the offset already integrated at every physics step
        AerialTask.after_step(self, physics)


#: the task class of each robot (``robot`` of :func:`build_environment`)
ROBOT_TASKS = {"kinematic": HexarotorWind, "rotor": RotorHexarotorWind}
ROBOTS = tuple(ROBOT_TASKS)


def build_environment(
    *, max_acceleration: float | None = MAX_ACCELERATION, robot: str = "kinematic", **options
) -> control.Environment:
    """The dm_control environment of ``hexarotor_wind``.

    Args:
        max_acceleration: force limit of the velocity servos per unit mass (m/s^2).
            ``None`` removes it: the servos are then linear (see :mod:`envs._aerial`),
            and the zero command still stops the robot within ``n_brk`` steps.
        robot: ``"kinematic"`` (level body, velocity servos) or ``"rotor"`` (six rotors and an onboard
            cascaded controller, :mod:`envs._rotor`; ``max_acceleration`` is for the kinematic robot only).
        **options: those of :func:`envs._task.task_environment`: ``empty`` (the wind stays), ``layout``
            (fixes the obstacles and the wind), ``seed``, ``episode_steps`` (default 400) and
            ``terminate_on_collision``.

    Returns:
        A ``dm_control.rl.control.Environment``.

    Raises:
        ValueError: an unknown ``robot``, or an acceleration limit other than the default for the rotor robot.

    Examples:
        >>> env = build_environment(layout=3)
        >>> env.reset().observation["obstacles_center"].shape
        (14, 3)
    """
    return aerial_environment(ROBOT_TASKS, robot, max_acceleration, **options)
