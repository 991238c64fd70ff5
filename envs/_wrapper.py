"""TorchRL wrapper of the dm_control tasks: float32 for learning, float64 on the safety path, nested
``obstacles``, bool flags."""
from __future__ import annotations

from copy import deepcopy

import mujoco
import numpy as np
import torch
from torchrl.data import Bounded, Composite
from torchrl.envs import DMControlWrapper

from envs._obstacles import Layout

_OBSTACLE_PREFIX = "obstacles_"


class RenderingUnavailable(RuntimeError):
    """Raised by :meth:`SafetyTaskEnv.render` when no OpenGL backend can be created."""


SAFETY_KEYS = ("state", "cost")
"""Entries kept in float64 (with every ``obstacles`` entry): what the safety layer checks, and the
constraint ``cost`` (float64, as in TorchRL's Safety-Gymnasium wrapper)."""


def _to_float32(spec):
    return spec.clone().to(torch.float32) if spec.dtype == torch.float64 else spec


def _keeps_float64(key: str) -> bool:
    return key in SAFETY_KEYS or key.startswith(_OBSTACLE_PREFIX)


class SafetyTaskEnv(DMControlWrapper):
    """A :class:`~torchrl.envs.DMControlWrapper` for the tasks of :mod:`envs`.

    Compared with ``DMControlWrapper`` followed by ``DoubleToFloat`` and a rename
    transform, it writes float32 tensors and the nested ``obstacles`` entry while
    reading the dm_control observation, which halves the per-step overhead. The robot
    ``state`` and the ``obstacles`` stay float64, as the task computes them, so the safety
    layer checks exactly what the task measured (no float32 rounding on the safety path).

    Output keys (``d`` position dim, ``K`` obstacle capacity, ``p`` generators):
    ``observation [obs_dim]``, ``state [n]``, ``obstacles`` (``center [K, d]``,
    ``generators [K, d, p]``, ``mask [K]`` bool), ``collision [1]`` bool,
    ``goal_reached [1]`` bool, ``speed [1]``, ``cost [1]`` (1.0 in contact with an obstacle,
    else 0.0: the per-step constraint signal of constrained RL, like the ``cost`` key of TorchRL's
    Safety-Gymnasium wrapper, here shaped like ``reward``), ``reward [1]``, ``done``/``terminated``/
    ``truncated [1]`` bool and, with ``from_pixels=True``, ``pixels [H, W, 3]`` uint8.
    Float entries are float32, except ``state``, ``obstacles`` and ``cost`` (float64).

    Args:
        env: a ``dm_control.rl.control.Environment`` whose task is a
            :class:`envs._task.SafetyTask`.
        **kwargs: ``DMControlWrapper`` keyword arguments (``from_pixels``,
            ``pixels_only``, ``camera_id``, ``render_kwargs``, ``device``...).

    Examples:
        >>> import envs
        >>> env = envs.make("point_circle", seed=0)
        >>> isinstance(env, SafetyTaskEnv)
        True
        >>> env.reset()["obstacles", "generators"].shape
        torch.Size([4, 2, 6])
    """

    def _make_specs(self, env) -> None:
        super()._make_specs(env)
        nested = Composite(shape=self.batch_size, device=self.device)
        obstacles = Composite(shape=self.batch_size, device=self.device)
        for key, spec in self.observation_spec.items():
            spec = spec if _keeps_float64(key) else _to_float32(spec)
            if key.startswith(_OBSTACLE_PREFIX):
                obstacles[key[len(_OBSTACLE_PREFIX) :]] = spec
            else:
                nested[key] = spec
        nested["obstacles"] = obstacles
        self.observation_spec = nested
        self.reward_spec = _to_float32(self.reward_spec)
        action = self.action_spec
        self.action_spec = Bounded(
            low=action.space.low.to(torch.float32),
            high=action.space.high.to(torch.float32),
            shape=action.shape,
            dtype=torch.float32,
            device=self.device,
        )

    def read_obs(self, observations):
        out, obstacles = {}, {}
        for key, value in observations.items():
            keep = _keeps_float64(key) or value.dtype != np.float64
            array = np.array(value, dtype=value.dtype if keep else np.float32)
            if key.startswith(_OBSTACLE_PREFIX):
                obstacles[key[len(_OBSTACLE_PREFIX) :]] = torch.from_numpy(array)
            else:
                out[key] = torch.from_numpy(array)
        out["obstacles"] = obstacles
        return out

    def read_reward(self, reward):
        return torch.tensor([0.0 if reward is None else reward], dtype=torch.float32)

    @property
    def physics(self):
        """The dm_control ``Physics`` of the task."""
        return self._env.physics

    def __deepcopy__(self, memo: dict) -> SafetyTaskEnv:
        """A copy that steps as this env would from here on: its own physics, task and random state.

        MuJoCo's copy of the simulation keeps its state (positions, velocities, controls) but not what was derived
        from it, such as the actuators' velocities, which dm_control's next step reads before deriving them again: a
        velocity servo's first step would push as if from rest. The copy derives them from its state
        (``Physics.forward``), and its task acts on its physics (:meth:`envs._task.SafetyTask.rebind`: a rotor robot's
        onboard controller), so its steps are the original's to the bit.
        """
        rebuild, args, state, *_ = self.__reduce_ex__(4)
        copied = rebuild(*args)
        memo[id(self)] = copied
        copied.__setstate__(deepcopy(state, memo))
        copied.physics.forward()
        copied.task.rebind(copied.physics)
        return copied

    @property
    def task(self):
        """The :class:`envs._task.SafetyTask` instance."""
        return self._env.task

    @property
    def layout(self) -> Layout:
        """The current episode's :class:`envs.Layout` (true geometry, goals, zonotopes)."""
        if self.task.layout is None:
            raise RuntimeError("call reset() before reading the layout")
        return self.task.layout

    def render(self, height: int = 240, width: int = 320, camera: str | int = "overview") -> np.ndarray:
        """An RGB frame of the current state.

        Args:
            height: image height in pixels.
            width: image width in pixels.
            camera: ``"overview"`` (top-down), ``"follow"`` (behind the robot) or an id.

        Returns:
            ``uint8`` array ``[height, width, 3]``.

        Raises:
            ValueError: unknown camera.
            RenderingUnavailable: no OpenGL backend (set ``MUJOCO_GL=egl`` or
                ``osmesa`` before importing ``envs``).
        """
        model = self.physics.model
        cameras = [model.id2name(i, "camera") for i in range(model.ncam)]
        if camera not in cameras and camera not in range(-1, model.ncam):
            raise ValueError(f"unknown camera {camera!r}; the model has {cameras}")
        try:
            return self.physics.render(height=height, width=width, camera_id=camera)
        except (ImportError, RuntimeError, OSError, AttributeError, mujoco.FatalError) as error:
            raise RenderingUnavailable(f"MuJoCo rendering is unavailable: {error}") from error
