"""Probabilistic ensemble world model (PETS-style): model, TensorDict wrapper, loss and training helper."""
from torchrl_brsl.models.ensemble import EnsembleLinear, ProbabilisticEnsemble, WorldModel, as_ensemble
from torchrl_brsl.models.loss import WorldModelLoss, train_world_model
from torchrl_brsl.models.normalizer import Normalizer

__all__ = ["EnsembleLinear", "Normalizer", "ProbabilisticEnsemble", "WorldModel", "WorldModelLoss", "as_ensemble",
           "train_world_model"]
