"""Task registry: :func:`make` and :func:`safety_info` by task name."""
from __future__ import annotations

import importlib
import inspect
from types import ModuleType

from torchrl.envs import EnvBase

from envs._safety_info import SafetyInfo
from envs._task import SafetyTask, task_environment
from envs._wrapper import SafetyTaskEnv
from envs.diffdrive_nav import DiffDriveNav
from envs.hexarotor_wind import HexarotorWind
from envs.point_boxes import PointBoxes
from envs.point_circle import PointCircle
from envs.quadrotor_nav import QuadrotorNav

_TASKS: dict[str, type[SafetyTask]] = {
    task.name: task for task in (PointCircle, DiffDriveNav, QuadrotorNav, HexarotorWind, PointBoxes)
}

#: names accepted by :func:`make` and :func:`safety_info`
TASKS: tuple[str, ...] = tuple(_TASKS)

#: arguments of every task's ``build_environment`` that :func:`make` fills itself
_MAKE_ARGS = ("empty", "layout", "seed")


def _task(name: str) -> type[SafetyTask]:
    try:
        return _TASKS[name]
    except KeyError:
        raise ValueError(f"unknown task {name!r}; choose one of {TASKS}") from None


def _module(name: str) -> ModuleType:
    """The module of task ``name``, with its ``build_environment``."""
    return importlib.import_module(_task(name).__module__)


def _keyword_options(function) -> set[str]:
    return {p.name for p in inspect.signature(function).parameters.values() if p.kind is p.KEYWORD_ONLY}


def _task_options(module: ModuleType) -> set[str]:
    """The task's arguments of :func:`make`: its own and those of :func:`envs._task.task_environment`."""
    return (_keyword_options(module.build_environment) | _keyword_options(task_environment)) - set(_MAKE_ARGS)


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
            ``diffdrive_nav``; ``robot``, ``"kinematic"`` or ``"rotor"``, for ``quadrotor_nav`` and
            ``hexarotor_wind``: :func:`safety_info` takes the same ``robot``) go to the
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
    task_kwargs = {key: kwargs.pop(key) for key in _task_options(module) if key in kwargs}
    environment = module.build_environment(empty=empty, layout=layout, seed=seed, **task_kwargs)
    env = SafetyTaskEnv(environment, **kwargs)
    if seed is not None:
        env.set_seed(seed)
    return env


def safety_info(name: str, robot: str | None = None) -> SafetyInfo:
    """What the safety layer needs to know about task ``name`` (see :class:`SafetyInfo`).

    Args:
        name: one of :data:`TASKS`.
        robot: the robot, as the ``robot`` argument of :func:`make` (``"wheeled"`` for ``diffdrive_nav``,
            ``"rotor"`` for ``quadrotor_nav`` and ``hexarotor_wind``); ``None``: the task's default robot.

    Raises:
        ValueError: an unknown task, or a robot the task does not have.

    Examples:
        >>> import envs
        >>> envs.safety_info("diffdrive_nav").n_brk, envs.safety_info("diffdrive_nav").n_plan
        (6, 8)
        >>> envs.safety_info("quadrotor_nav").n_brk, envs.safety_info("quadrotor_nav", robot="rotor").n_brk
        (10, 16)
    """
    task = _task(name)
    if robot is None:
        return task.safety_info()
    robots = getattr(_module(name), "ROBOT_TASKS", {"kinematic": task})
    if robot not in robots:
        raise ValueError(f"unknown robot {robot!r} for {name}; choose one of {tuple(robots)}")
    return robots[robot].safety_info()
