"""The training / evaluation env: the task, an episode-reward counter and the safety layer (BRSL's, or a
baseline's)."""
from __future__ import annotations

from omegaconf import DictConfig
from torchrl.envs import Compose, RewardSum, TransformedEnv

from recipes import baselines
from recipes.safety_models import SafetyModels, make_layer
from recipes.tasks import make_base_env


def make_env(cfg: DictConfig, seed: int, models: SafetyModels | dict | None = None, layout: int | None = None,
             evaluation: bool = False):
    """The task, an episode-reward counter and, with ``models``, the layer (BRSL's, or a baseline's:
    ``models`` is then the dict of :func:`recipes.baselines.fit`).

    ``episode_reward`` sums the task's reward before the layer's penalty (the paper's metric).
    ``evaluation``: SAILR's interventions no longer end the episode.
    """
    transforms = [RewardSum(in_keys=["reward"], out_keys=["episode_reward"])]
    if models is not None:
        transforms.append(make_layer(cfg, models) if cfg.method.layer
                          else baselines.make_transform(cfg, models, evaluation=evaluation))
    return TransformedEnv(make_base_env(cfg.task, seed, layout=layout), Compose(*transforms))


class EnvFactory:
    """Picklable :func:`make_env` for collector processes."""

    def __init__(self, cfg: DictConfig, seed: int, models: SafetyModels | dict | None):
        self.cfg, self.seed, self.models = cfg, seed, models

    def __call__(self):
        return make_env(self.cfg, self.seed, self.models)
