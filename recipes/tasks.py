"""A task from its config (``cfg.task``): the bare env, its kind, and its random-input offline data, from
which BRSL's reachability models and the baselines' models are fitted."""
from __future__ import annotations

import hashlib
import json
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig, OmegaConf

import envs
from torchrl_brsl.reach import collect_offline_data, load_offline_data, save_offline_data


def make_base_env(task: DictConfig, seed: int, *, layout: int | None = None, empty: bool = False, **kwargs):
    """``envs.make`` with the task options of the config (``task.env``, ``task.episode_steps`` unless null)."""
    options = dict(OmegaConf.to_container(task.env, resolve=True) or {})
    if not empty and task.get("episode_steps") is not None:
        options["episode_steps"] = int(task.episode_steps)
    options.update(kwargs)
    return envs.make(task.name, seed=seed, empty=empty, layout=layout, **options)


def task_info(task: DictConfig) -> envs.SafetyInfo:
    """``envs.safety_info`` of the task's robot (``task.env.robot``, the task's default when absent)."""
    return envs.safety_info(task.name, robot=(task.get("env") or {}).get("robot"))


def task_kind(task: DictConfig) -> str:
    """``"goal"`` (Table I: diffdrive_nav, quadrotor_nav) or ``"path"`` (Table II)."""
    return str(task.kind)


def uniform_policy(low: torch.Tensor, high: torch.Tensor):
    """Actions drawn uniformly from ``[low, high]`` (offline data collection)."""

    def policy(td):
        td["action"] = low + (high - low) * torch.rand_like(low)
        return td

    return policy


def regime_policy(task: DictConfig, max_speed: float):
    """Random inputs that brake (with the task's braking policy) whenever the speed exceeds ``max_speed``.

    Keeps the offline data in the operating regime: e.g. ``point_circle`` below its 2 m/s speed
    saturation, where its dynamics are linear and the data-driven sets stay tight.
    """
    info = task_info(task)
    low, high = info.action_low, info.action_high
    uniform = uniform_policy(low, high)

    def policy(td):
        state = td["state"]
        if state[list(info.velocity_dims)].norm() > max_speed:
            td["action"] = info.braking_policy(state.double()).float().clamp(low, high)
            return td
        return uniform(td)

    return policy


def local_domain(task: DictConfig) -> tuple[torch.Tensor, torch.Tensor]:
    """``(low, high)`` ``[n + m]`` of ``task.local`` (``null`` bounds: unbounded)."""
    info = task_info(task)
    bounds = []
    for side, default in (("low", -np.inf), ("high", np.inf)):
        state = task.local.get(f"state_{side}") or [default] * info.state_dim
        action = task.local.get(f"action_{side}") or [default] * info.action_dim
        bounds.append(torch.tensor([float(v) for v in [*state, *action]], dtype=torch.float64))
    return bounds[0], bounds[1]


def offline_data(task: DictConfig, cache_dir: str | Path, seed: int = 0, local: bool = False):
    """Random-input transitions in the empty task, cached on disk.

    ``task.offline.steps`` of them for the main model, or with ``local``, ``task.local.steps``
    with inputs drawn inside the local domain's action bounds; ``episode_steps`` (when set) ends
    each offline episode that soon, so the data see more of what a reset draws (a new wind). The
    cache key covers the task config, the state layout, the seed and the model kind.
    """
    options = task.local if local else task.offline
    info = task_info(task)
    spec = {"task": task.name, "state_dim": info.state_dim, "env": OmegaConf.to_container(task.env, resolve=True),
            "offline": OmegaConf.to_container(options, resolve=True), "seed": seed, "local": local}
    digest = hashlib.sha1(json.dumps(spec, sort_keys=True).encode()).hexdigest()[:10]
    path = Path(cache_dir) / f"{task.name}-{'local-' if local else ''}{digest}"
    if (path / "meta.json").exists():
        return load_offline_data(path)
    torch.manual_seed(seed)
    if local:
        low, high = local_domain(task)
        policy = uniform_policy(torch.maximum(info.action_low, low[info.state_dim:].float()),
                                 torch.minimum(info.action_high, high[info.state_dim:].float()))
    else:
        max_speed = task.offline.get("max_speed")
        policy = regime_policy(task, float(max_speed)) if max_speed is not None else None
    episode = {} if options.get("episode_steps") is None else {"episode_steps": int(options.episode_steps)}
    data = collect_offline_data(make_base_env(task, seed + 12345, empty=True, **episode), int(options.steps),
                                policy=policy)
    path.parent.mkdir(parents=True, exist_ok=True)
    save_offline_data(data, path)
    return data
