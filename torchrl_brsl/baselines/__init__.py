"""The paper's comparison methods as TorchRL transforms: SECAS, SAILR and RTS.

Each reads the robot ``state`` and the task's ``obstacles`` from the TensorDict, replaces the
proposed ``action`` by the one it executes, and writes ``next["safe_action"]`` and its
diagnostics (``intervened``, ``compute_time``) under ``diagnostics_key``, like
:class:`~torchrl_brsl.safety.BRSLSafetyLayer`; safety decisions are made in float64.

* :class:`SECASSafetyLayer`: Dalal et al. (2018), a learned linear constraint model and a
  closed-form correction;
* :class:`SAILRIntervener`: Wagener et al. (2021), a backup policy takes over when the cost
  advantage estimated with a nominal model exceeds ``eta``, and the learner's episode ends;
* :class:`RTSSafeguard`: Shao et al. (2021), parameterised braking trajectories with offline
  reachable sets per parameter cell (:class:`TrajectoryReachableSets`), checked with the
  project's zonotope collision check.

SAILR and RTS need a robot model: :class:`AffineModel`, the least-squares affine fit of the same
random-input offline data BRSL gets.
"""
from torchrl_brsl.baselines._common import ActionFilter, AffineModel, point_clearance
from torchrl_brsl.baselines.rts import RTSSafeguard, TrajectoryReachableSets
from torchrl_brsl.baselines.sailr import SAILRIntervener, rollout_cost
from torchrl_brsl.baselines.secas import (
    LinearSafetyModel,
    SECASSafetyLayer,
    fit_safety_model,
    obstacle_features,
    secas_correction,
)

__all__ = [
    "ActionFilter",
    "AffineModel",
    "LinearSafetyModel",
    "RTSSafeguard",
    "SAILRIntervener",
    "SECASSafetyLayer",
    "TrajectoryReachableSets",
    "fit_safety_model",
    "obstacle_features",
    "point_clearance",
    "rollout_cost",
    "secas_correction",
]
