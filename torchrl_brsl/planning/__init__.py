"""Rollout planner: rolls a policy through the world model and writes the ``plan``."""
from torchrl_brsl.planning.rollout import PROPAGATIONS, RolloutPlanner

__all__ = ["PROPAGATIONS", "RolloutPlanner"]
