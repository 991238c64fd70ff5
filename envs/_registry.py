"""Task registry: :func:`make` and :func:`safety_info` by task name."""
from __future__ import annotations

import inspect
from types import ModuleType

from torchrl.envs import EnvBase

from envs import diffdrive_nav, hexarotor_wind, point_boxes, point_circle, quadrotor_nav
from envs._safety_info import SafetyInfo
from envs._wrapper import SafetyTaskEnv

_TASKS: dict[str, ModuleType] = {
    "point_circle": point_circle,
    "diffdrive_nav": diffdrive_nav,
    "quadrotor_nav": quadrotor_nav,
    "hexarotor_wind": hexarotor_wind,
    "point_boxes": point_boxes,
}

#: names accepted by :func:`make` and :func:`safety_info`
TASKS: tuple[str, ...] = tuple(_TASKS)

#: arguments of every task's ``build_environment`` that :func:`make` fills itself
_MAKE_ARGS = ("empty", "layout", "seed")


def _module(name: str) -> ModuleType:
    try:
        return _TASKS[name]
    except KeyError:
        raise ValueError(f"unknown task {name!r}; choose one of {TASKS}") from None


def make(name: str, seed: int | None = 0, empty: bool = False, layout: int | None = None, **kwargs) -> EnvBase:
    """Builds a task as a TorchRL environment.

    Args:
        name: one of :data:`TASKS`.
        seed: seed of the environment (layouts, start states, noise); the same seed
            gives the same sequence of episodes. ``None`` leaves it unseeded.
        empty: the obstacle-free variant used to collect offline data: obstacle
            mask all False, random start velocities, episodes truncated when the
            robot leaves the data region.
        layout: index of a fixed evaluation layout (obstacles, goal, start; for
            ``hexarotor_wind`` also the wind), identical for every seed and reset.
        **kwargs: arguments of the task module's ``build_environment``
            (``episode_steps``, the time limit in control steps, and
            ``terminate_on_collision`` for every task; ``max_acceleration`` for
            ``point_boxes``, ``diffdrive_nav``, ``quadrotor_nav`` and ``hexarotor_wind``;
            ``max_turn_acceleration`` and ``robot``, ``"kinematic"`` or ``"wheeled"``, for
            ``diffdrive_nav``) go to the
            task; anything else (``from_pixels``, ``pixels_only``, ``camera_id``,
            ``render_kwargs``, ``device``) to :class:`~torchrl.envs.DMControlWrapper`.

    Returns:
        A :class:`envs.SafetyTaskEnv` (an ``EnvBase``; append transforms with
        ``env.append_transform``).

    Examples:
        >>> import envs
        >>> env = envs.make("diffdrive_nav", seed=0)
        >>> td = env.reset()
        >>> td["state"].shape, td["obstacles", "center"].shape, td["obstacles", "generators"].shape
        (torch.Size([6]), torch.Size([12, 2]), torch.Size([12, 2, 6]))
        >>> env.rollout(3)["next", "collision"].shape
        torch.Size([3, 1])
    """
    module = _module(name)
    task_args = set(inspect.signature(module.build_environment).parameters) - set(_MAKE_ARGS)
    task_kwargs = {key: kwargs.pop(key) for key in task_args if key in kwargs}
    environment = module.build_environment(empty=empty, layout=layout, seed=seed, **task_kwargs)
    env = SafetyTaskEnv(environment, **kwargs)
    if seed is not None:
        env.set_seed(seed)
    return env


def safety_info(name: str) -> SafetyInfo:
    """What the safety layer needs to know about task ``name`` (see :class:`SafetyInfo`).

    Examples:
        >>> import envs
        >>> envs.safety_info("diffdrive_nav").n_brk, envs.safety_info("diffdrive_nav").n_plan
        (6, 8)
    """
    return _module(name).safety_info()
