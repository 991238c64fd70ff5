"""Offline data for data-driven reachability: random inputs in an empty copy of the task."""
from __future__ import annotations

from pathlib import Path
from typing import Callable

import torch
from tensordict import TensorDict
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.envs import EnvBase
from tqdm.auto import tqdm


def collect_offline_data(env: EnvBase, steps: int = 500, *, state_key: NestedKey = "state",
                         action_key: NestedKey = "action", policy=None, progress: bool = False,
                         generator: torch.Generator | None = None,
                         record: Callable[[EnvBase], Tensor] | None = None) -> TensorDict:
    """Collect ``steps`` transitions of random inputs (paper Sec. IV "Setup").

    The robot is driven by uniformly random actions (or ``policy``) in an obstacle-free
    copy of the task; whenever the env ends an episode (e.g. the robot left the data
    region) it is reset and collection continues. Only transitions within an episode are kept.

    Args:
        env: an unbatched TorchRL env (typically the task's empty variant).
        steps: number of transitions to collect.
        state_key: where the robot state is.
        action_key: the action entry.
        policy: optional ``TensorDict -> TensorDict`` module writing ``action_key``; default
            ``env.rand_action`` (the global torch RNG), or with ``generator`` uniform actions
            in the bounds of the action spec.
        progress: show a progress bar.
        generator: the source of the random actions (``torch.Generator``), so that a
            collection is reproducible without seeding the global RNG; the env's own
            randomness (initial states, noise) comes from ``env.set_seed``.
        record: called with the env after each step; its values are kept under ``recorded`` (e.g. the noise a
            task of ``envs`` added, for :func:`~torchrl_brsl.reach.noiseless_transitions`).

    Returns:
        A TensorDict of batch ``[steps]`` with ``x_minus``, ``x_plus`` (``[steps, n]``) and
        ``u_minus`` (``[steps, m]``), in float64 (and ``recorded``, with ``record``).

    Examples:
        >>> data = collect_offline_data(envs.make("diffdrive_nav", empty=True), steps=500)
        >>> data["x_minus"].shape
        torch.Size([500, 6])
    """
    if steps < 1:
        raise ValueError(f"`steps` must be positive, got {steps}")
    if env.batch_size != torch.Size([]):
        raise ValueError(f"`env` must be unbatched, got batch size {tuple(env.batch_size)}")
    if policy is None and generator is not None:
        spec = env.full_action_spec[action_key]
        low, high = spec.space.low, spec.space.high

        def policy(td):  # noqa: F811 - uniform in the action box, from ``generator``
            u = torch.rand(low.shape, generator=generator, dtype=torch.float64)
            return td.set(action_key, (low.double() + (high.double() - low.double()) * u).to(spec.dtype))
    x_minus, x_plus, u_minus, recorded = [], [], [], []
    td = env.reset()
    bar = tqdm(total=steps, desc="offline data", disable=not progress)
    while len(x_minus) < steps:
        td = policy(td) if policy is not None else env.rand_action(td)
        td = env.step(td)
        x_minus.append(td.get(state_key))
        u_minus.append(td.get(action_key))
        x_plus.append(td.get(("next", state_key)))
        if record is not None:
            recorded.append(torch.as_tensor(record(env)))
        bar.update(1)
        td = env.step_mdp(td) if not bool(td.get(("next", "done")).any()) else env.reset()
    bar.close()
    stack = lambda items: torch.stack(items).to(torch.float64)  # noqa: E731
    data = TensorDict(x_minus=stack(x_minus), x_plus=stack(x_plus), u_minus=stack(u_minus), batch_size=[steps])
    if record is not None:
        data["recorded"] = stack(recorded)
    return data


def save_offline_data(data: TensorDict, path: str | Path) -> None:
    """Write offline data to ``path`` (a directory, memory-mapped TensorDict)."""
    data.memmap(str(path))


def load_offline_data(path: str | Path) -> TensorDict:
    """Read data written by :func:`save_offline_data`."""
    return TensorDict.load_memmap(str(path)).to_tensordict()
