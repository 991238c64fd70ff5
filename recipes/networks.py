"""TD3's networks (actor, critic), its exploration noise, and the optional world-model planner."""
from __future__ import annotations

import warnings
from typing import NamedTuple

import torch
from omegaconf import DictConfig
from tensordict.nn import TensorDictModule, TensorDictModuleBase, TensorDictSequential
from torch import nn
from torchrl.modules import MLP, AdditiveGaussianModule, TanhModule, ValueOperator
from torchrl.objectives import LossModule

from recipes.safety_models import horizon
from torchrl_brsl.modules import DampedGaussianModule

#: ``exploration.schedule``: the noise module
SCHEDULES = {"geometric": DampedGaussianModule, "linear": AdditiveGaussianModule}


def make_actor(env, hidden) -> TensorDictSequential:
    """Deterministic actor ``observation [d] -> action [m]``, squashed into the action bounds."""
    spec = env.full_action_spec["action"]
    net = MLP(in_features=env.observation_spec["observation"].shape[-1], out_features=spec.shape[-1],
              num_cells=list(hidden), activation_class=nn.ReLU)
    return TensorDictSequential(TensorDictModule(net, in_keys=["observation"], out_keys=["param"]),
                                TanhModule(in_keys=["param"], out_keys=["action"], spec=spec))


def make_qvalue(env, hidden) -> ValueOperator:
    """Critic ``(observation [d], action [m]) -> state_action_value [1]``."""
    in_features = env.observation_spec["observation"].shape[-1] + env.full_action_spec["action"].shape[-1]
    net = MLP(in_features=in_features, out_features=1, num_cells=list(hidden), activation_class=nn.ReLU)
    return ValueOperator(net, in_keys=["observation", "action"], out_keys=["state_action_value"])


def make_exploration(exploration: DictConfig, env) -> TensorDictModuleBase:
    """Gaussian noise on ``action``, in units of half the action range, annealed from ``sigma_init`` to
    ``sigma_end`` over ``annealing_frames`` (``exploration.schedule``: geometric or linear)."""
    if exploration.schedule not in SCHEDULES:
        raise ValueError(f"exploration.schedule must be one of {list(SCHEDULES)}, got {exploration.schedule!r}")
    spec = env.full_action_spec["action"]
    with warnings.catch_warnings():  # TorchRL copies the per-dim `std` tensor with torch.tensor
        warnings.filterwarnings("ignore", message="To copy construct from a tensor")
        return SCHEDULES[exploration.schedule](spec, sigma_init=float(exploration.sigma_init),
                                               sigma_end=float(exploration.sigma_end),
                                               annealing_num_steps=exploration.annealing_frames,
                                               std=(spec.space.high - spec.space.low) / 2)


class Planner(NamedTuple):
    """``method.planner=ensemble``: ``rollout`` rolls the noisy actor through ``world_model`` (a probabilistic
    ensemble) for ``n_plan`` steps and writes ``plan`` ``[n_plan, m]`` and ``action``; the world model learns
    from the replay buffer with ``loss`` and ``optimiser``."""

    rollout: TensorDictModuleBase
    world_model: nn.Module
    loss: LossModule
    optimiser: torch.optim.Optimizer

    def update(self, buffer, ensemble: DictConfig) -> float:
        """``ensemble.updates_per_batch`` steps on minibatches of ``buffer``; returns the mean loss."""
        from torchrl_brsl.models import train_world_model

        losses = train_world_model(self.world_model, self.loss, buffer, ensemble.updates_per_batch, self.optimiser,
                                   batch_size=ensemble.batch_size)
        return losses.mean().item()


def make_planner(cfg: DictConfig, policy, env) -> Planner | None:
    """``method.planner``: ``none`` (None: the action is a one-step plan) or ``ensemble``, a :class:`Planner`
    with a probabilistic ensemble (paper Sec. IV: 4 layers of 200, leaky ReLU) rolling ``policy``."""
    if cfg.method.planner == "none":
        return None
    if cfg.method.planner != "ensemble":
        raise ValueError(f"`method.planner` must be 'none' or 'ensemble', got {cfg.method.planner!r}")
    try:
        from torchrl_brsl.models import ProbabilisticEnsemble, WorldModelLoss
        from torchrl_brsl.planning import RolloutPlanner
    except ImportError as error:
        raise NotImplementedError("method.planner=ensemble needs torchrl_brsl.models and torchrl_brsl.planning, "
                                  "which this installation does not provide; use method.planner=none") from error
    ens = cfg.method.ensemble
    model = ProbabilisticEnsemble(env.observation_spec["observation"].shape[-1],
                                  env.full_action_spec["action"].shape[-1], ensemble_size=ens.size,
                                  hidden_size=ens.hidden_size, num_layers=ens.num_layers)
    rollout = RolloutPlanner(policy, model, n_plan=horizon(cfg)[0])
    return Planner(rollout, model, WorldModelLoss(model), torch.optim.Adam(model.parameters(), lr=ens.lr))
