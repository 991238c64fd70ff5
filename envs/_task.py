"""Episode logic shared by the tasks (a dm_control ``base.Task`` subclass).

Subclasses supply the robot: how an action drives the physics, how state-space noise
is written back into the physics, what the state and the policy observation are, the
layout sampler and the reward. This class supplies layouts and seeding, process
noise, collision detection from MuJoCo contacts, the data region of the empty
variant and the observation dictionary read by :class:`envs._wrapper.SafetyTaskEnv`, including
the per-step constraint ``cost`` (1 in contact with an obstacle, else 0), as TorchRL's
Safety-Gymnasium wrapper exposes it for constrained RL.
"""
from __future__ import annotations

import collections
from typing import Callable, ClassVar

import mujoco
import numpy as np
import torch
from dm_control import mujoco as dm_mujoco
from dm_control.rl import control
from dm_control.suite import base
from dm_env import specs

from envs._obstacles import GENERATORS_PER_OBSTACLE, Layout, ObstacleSlots, zonotope_batch
from envs._safety_info import SafetyInfo


class SafetyTask(base.Task):
    """Base task: a robot among obstacles with process noise.

    The class attributes describe the task; :meth:`safety_info` hands the safety layer's share of
    them on as a :class:`SafetyInfo`, whose attributes of the same names document them
    (``n_brk``, ``n_plan``, ``braking_action``, :meth:`braking_policy`, ``stop_tolerance``, ...).
    ``episode_steps`` is the default time limit of :func:`task_environment`, ``physics_class`` the
    dm_control ``Physics`` (sub)class it builds the model with.

    Args:
        empty: no obstacles (obstacle mask all False); episodes are truncated when
            the robot leaves the data region, and start from random velocities.
        layout: index of a fixed evaluation layout (independent of the seed), or
            ``None`` for a layout drawn from the task's random state each episode.
        terminate_on_collision: end the episode (``terminated``) on a collision.
        random: seed or ``numpy.random.RandomState``.

    Attributes:
        noise_scale: multiplies the process noise; 0 gives noiseless replays (tests).
        noise_signs: ``None`` (each step's noise drawn uniformly in ``W``) or ``[p]`` signs of the noise
            generators: every step's noise at that vertex of ``W``, a constant worst case that reaches the edges of
            the reachable sets, which uniform noise seldom does (``torchrl_brsl.reach.env_sample_reach``).
        last_noise: ``[n]`` the noise added to the state by the last step (zeros without noise), so that
            ``next state - last_noise`` is the noiseless successor (checks of a model at the noise's worst,
            ``benchmarks/bench_task_soundness.py``).
    """

    name: ClassVar[str]
    layout_code: ClassVar[int]
    dt: ClassVar[float] = 0.1
    obstacle_dim: ClassVar[int]
    capacity: ClassVar[int]
    robot_radius: ClassVar[float]
    observation_dim: ClassVar[int]
    action_low: ClassVar[np.ndarray]
    action_high: ClassVar[np.ndarray]
    noise_center: ClassVar[np.ndarray]
    noise_generators: ClassVar[np.ndarray]
    position_dims: ClassVar[tuple[int, ...]]
    velocity_dims: ClassVar[tuple[int, ...]]
    heading_dims: ClassVar[tuple[int, ...]] = ()
    obstacle_kinds: ClassVar[tuple[str, ...]]
    episode_steps: ClassVar[int]
    n_brk: ClassVar[int]
    n_plan: ClassVar[int]
    braking_action: ClassVar[np.ndarray]
    stop_tolerance: ClassVar[float]
    physics_class: ClassVar[type[dm_mujoco.Physics]] = dm_mujoco.Physics

    def __init__(
        self,
        *,
        empty: bool = False,
        layout: int | None = None,
        terminate_on_collision: bool = True,
        random=None,
    ):
        super().__init__(random=random)
        self.empty = bool(empty)
        self.layout_index = layout
        self.terminate_on_collision = bool(terminate_on_collision)
        self.noise_scale = 1.0
        self.noise_signs: np.ndarray | None = None
        self.last_noise = np.zeros(len(self.noise_center))
        self.layout: Layout | None = None
        self._slots: ObstacleSlots | None = None
        self._robot_geoms: np.ndarray | None = None
        self._collision = False
        self._goal_reached = False
        self._first_step = True
        self._obstacle_arrays = zonotope_batch([], self.robot_radius, self.obstacle_dim, self.capacity)

    # ------------------------------------------------------------------ robot hooks
    def _bind(self, physics) -> None:
        """Caches model ids; called once per physics."""

    def rebind(self, physics) -> None:
        """Act on ``physics`` from now on: a copy of the one the task was bound to, with the same model
        (:meth:`envs.SafetyTaskEnv.__deepcopy__`). Only a task that holds the physics' data itself (a rotor robot's
        onboard controller) has anything to re-point; the others read the physics each call passes them."""

    def _new_layout(self, rng: np.random.RandomState) -> Layout:
        raise NotImplementedError

    def _reset_robot(self, physics, rng: np.random.RandomState) -> None:
        raise NotImplementedError

    def _apply_action(self, action: np.ndarray, physics) -> None:
        raise NotImplementedError

    def _add_state_noise(self, physics, noise: np.ndarray) -> None:
        raise NotImplementedError

    def state(self, physics) -> np.ndarray:
        """The robot state ``[n]`` used by reachability (position dims first)."""
        raise NotImplementedError

    def _policy_observation(self, physics) -> np.ndarray:
        raise NotImplementedError

    def _speed(self, physics) -> float:
        raise NotImplementedError

    def _update_progress(self, physics) -> None:
        """Updates goal bookkeeping after a step; sets ``self._goal_reached``."""

    def _in_data_region(self, physics) -> bool:
        raise NotImplementedError

    # ------------------------------------------------------------------ dm_control API
    def action_spec(self, physics):
        return specs.BoundedArray(
            shape=self.action_low.shape,
            dtype=np.float64,
            minimum=self.action_low,
            maximum=self.action_high,
            name="action",
        )

    def observation_spec(self, physics):
        k, d, p = self.capacity, self.obstacle_dim, GENERATORS_PER_OBSTACLE[self.obstacle_dim]
        return collections.OrderedDict(
            observation=specs.Array((self.observation_dim,), np.float64, "observation"),
            state=specs.Array((len(self.noise_center),), np.float64, "state"),
            obstacles_center=specs.Array((k, d), np.float64, "obstacles_center"),
            obstacles_generators=specs.Array((k, d, p), np.float64, "obstacles_generators"),
            obstacles_mask=specs.Array((k,), bool, "obstacles_mask"),
            collision=specs.Array((1,), bool, "collision"),
            goal_reached=specs.Array((1,), bool, "goal_reached"),
            speed=specs.Array((1,), np.float64, "speed"),
            cost=specs.Array((1,), np.float64, "cost"),
        )

    def initialize_episode(self, physics):
        if self._robot_geoms is None:
            root = physics.model.name2id("robot", "body")
            self._robot_geoms = np.flatnonzero(physics.model.geom_bodyid == root)
            if not self.empty:
                self._slots = ObstacleSlots(physics, self.obstacle_kinds)
            self._bind(physics)
        rng = self.random if self.layout_index is None else np.random.RandomState([self.layout_code, self.layout_index])
        self.layout = self._new_layout(rng)
        if self._slots is not None:
            self._slots.apply(physics, self.layout.obstacles)
        self._obstacle_arrays = (
            self.layout.obstacle_center,
            self.layout.obstacle_generators,
            self.layout.obstacle_mask,
        )
        self._goal_reached = False
        self._reset_robot(physics, rng)
        physics.forward()
        self._collision = self._in_contact(physics)
        self._first_step = True

    def before_step(self, action, physics):
        if self._first_step:
            # dm_control's after_reset runs mj_forward with actuation disabled, which
            # leaves actuator velocities at 0; the velocity servos need them.
            physics.forward()
            self._first_step = False
        action = np.clip(np.asarray(action, dtype=np.float64), self.action_low, self.action_high)
        self._apply_action(action, physics)

    def after_step(self, physics):
        self.last_noise = np.zeros(len(self.noise_center))
        if self.noise_scale:
            z = self.noise_signs if self.noise_signs is not None else self.random.uniform(
                -1.0, 1.0, self.noise_generators.shape[1])
            self.last_noise = self.noise_scale * (self.noise_center + self.noise_generators @ z)
            self._add_state_noise(physics, self.last_noise)
            mujoco.mj_fwdVelocity(physics.model.ptr, physics.data.ptr)
        self._collision = self._in_contact(physics)
        self._update_progress(physics)

    def get_observation(self, physics):
        center, generators, mask = self._obstacle_arrays
        return collections.OrderedDict(
            observation=self._policy_observation(physics),
            state=self.state(physics),
            obstacles_center=center,
            obstacles_generators=generators,
            obstacles_mask=mask,
            collision=np.array([self._collision]),
            goal_reached=np.array([self._goal_reached]),
            speed=np.array([self._speed(physics)]),
            cost=np.array([float(self._collision)]),
        )

    def get_termination(self, physics):
        if self._goal_reached or (self._collision and self.terminate_on_collision):
            return 0.0
        if self.empty and not self._in_data_region(physics):
            return 1.0
        return None

    # ------------------------------------------------------------------ contacts, zonotopes, SafetyInfo
    def _in_contact(self, physics) -> bool:
        """Whether any robot geom touches an obstacle geom (MuJoCo contacts)."""
        data = physics.data
        if data.ncon == 0:
            return False
        return bool(np.isin(data.contact.geom[: data.ncon], self._robot_geoms).any())

    def _layout_zonotopes(self, obstacles) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
        return zonotope_batch(obstacles, self.robot_radius, self.obstacle_dim, self.capacity)

    @classmethod
    def braking_policy(cls, state: torch.Tensor) -> torch.Tensor:
        """Stops the robot within ``n_brk`` steps: here by holding ``braking_action`` (velocity commands).

        Args:
            state: ``[..., n]``.

        Returns:
            Actions ``[..., m]`` with the dtype and device of ``state``.
        """
        action = torch.as_tensor(cls.braking_action, dtype=state.dtype, device=state.device)
        return action.expand(*state.shape[:-1], -1).clone()

    @classmethod
    def safety_info(cls) -> SafetyInfo:
        """The task's :class:`SafetyInfo`, from its class attributes."""

        def as_tensor(array) -> torch.Tensor:
            return torch.as_tensor(np.asarray(array), dtype=torch.float32)

        return SafetyInfo(
            name=cls.name,
            state_dim=len(cls.noise_center),
            action_dim=len(cls.action_low),
            position_dims=tuple(cls.position_dims),
            velocity_dims=tuple(cls.velocity_dims),
            obstacle_dim=cls.obstacle_dim,
            action_low=as_tensor(cls.action_low),
            action_high=as_tensor(cls.action_high),
            noise_center=as_tensor(cls.noise_center),
            noise_generators=as_tensor(cls.noise_generators),
            n_brk=cls.n_brk,
            n_plan=cls.n_plan,
            braking_action=as_tensor(cls.braking_action),
            braking_policy=cls.braking_policy,
            stop_tolerance=float(cls.stop_tolerance),
            dt=cls.dt,
            heading_dims=tuple(cls.heading_dims),
        )


class GoalTask(SafetyTask):
    """A :class:`SafetyTask` with goal regions to reach in order.

    ``layout.goals [G, d]`` are visited in order; the episode ends (``terminated``,
    ``goal_reached=True``) when the robot centre has been within ``goal_radius`` of
    each. Reward per step: ``progress_scale * (decrease of the distance to the current
    goal) + GOAL_BONUS * (goals reached this step) - COLLISION_PENALTY * collision``.
    """

    GOAL_BONUS: ClassVar[float] = 10.0
    COLLISION_PENALTY: ClassVar[float] = 10.0
    progress_scale: ClassVar[float] = 1.0

    def position(self, physics) -> np.ndarray:
        """Robot position ``[d]``."""
        raise NotImplementedError

    @property
    def goal_index(self) -> int:
        """Index of the goal the robot heads for (``G`` once all are reached)."""
        return self._goal_index

    def current_goal(self) -> np.ndarray:
        """Centre ``[d]`` of the goal the robot heads for (the last one once all are reached)."""
        goals = self.layout.goals
        return goals[min(self._goal_index, len(goals) - 1)]

    def initialize_episode(self, physics):
        self._goal_index = 0
        self._reached_now = 0
        self._distance = self._progress = 0.0
        super().initialize_episode(physics)
        self._distance = self._goal_distance(physics)

    def before_step(self, action, physics):
        self._distance = self._goal_distance(physics)
        super().before_step(action, physics)

    def _goal_distance(self, physics) -> float:
        return float(np.linalg.norm(self.position(physics) - self.current_goal()))

    def _update_progress(self, physics) -> None:
        distance = self._goal_distance(physics)
        self._progress = self._distance - distance
        self._reached_now = 0
        if distance <= self.layout.goal_radius:
            self._reached_now = 1
            self._goal_index += 1
            self._goal_reached = self._goal_index == len(self.layout.goals)

    def get_reward(self, physics) -> float:
        return float(
            self.progress_scale * self._progress
            + self.GOAL_BONUS * self._reached_now
            - self.COLLISION_PENALTY * self._collision
        )


def task_environment(
    task: type[SafetyTask],
    model: Callable[..., str],
    *,
    empty: bool = False,
    layout: int | None = None,
    seed=None,
    episode_steps: int | None = None,
    terminate_on_collision: bool = True,
    **model_options,
) -> control.Environment:
    """The dm_control environment of a task: what every task module's ``build_environment`` does.

    Args:
        task: the task class.
        model: ``model(empty, **model_options)``, the MJCF model of the task; its timestep sets the
            physics steps per control step of ``task.dt``.
        empty: the obstacle-free variant for offline data collection.
        layout: fixed evaluation layout index, or None for a layout drawn each episode.
        seed: seed of the task's random state.
        episode_steps: time limit in control steps (``None``: ``task.episode_steps``).
        terminate_on_collision: end the episode on a collision.
        **model_options: the task's own options, for ``model``.

    Returns:
        A ``dm_control.rl.control.Environment``.
    """
    physics = task.physics_class.from_xml_string(model(empty, **model_options))
    instance = task(empty=empty, layout=layout, terminate_on_collision=terminate_on_collision, random=seed)
    steps = task.episode_steps if episode_steps is None else episode_steps
    return control.Environment(physics, instance, time_limit=(steps - 0.5) * task.dt,
                               n_sub_steps=round(task.dt / physics.timestep()))
