"""A recipe's set-up: the composed config, seeds and torch threads."""
from __future__ import annotations

import os
import random
from pathlib import Path

import numpy as np
import torch
from omegaconf import DictConfig

CONFIG_DIR = Path(__file__).resolve().parent / "config"


def compose_config(overrides: list[str] | None = None, config_name: str = "train") -> DictConfig:
    """The training config with Hydra overrides, without running Hydra (tests, demo)."""
    from hydra import compose, initialize_config_dir

    with initialize_config_dir(config_dir=str(CONFIG_DIR), version_base=None):
        return compose(config_name=config_name, overrides=list(overrides or []))


def seed_everything(seed: int) -> None:
    random.seed(seed)
    np.random.seed(seed)
    torch.manual_seed(seed)


def threads(n: int) -> None:
    """Small MLPs run several times faster on one thread than on two."""
    torch.set_num_threads(int(n))
    os.environ.setdefault("OMP_NUM_THREADS", str(n))
