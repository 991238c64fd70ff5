"""SAILR: advantage-based intervention with a backup policy.

Wagener, Boots, Cheng, "Safe reinforcement learning using advantage-based intervention",
ICML 2021; reference code ``nolanwagener/safe_rl`` (the point-robot intervener).

A backup policy ``μ`` (the task's braking policy, e.g. ``a = clip(-v / dt)`` for the
double integrator, zero command for velocity-commanded robots) and the cost advantage
``A_c(s, a) = Q_c^μ(s, a) - V_c^μ(s)``, with cost 1 for a trajectory that hits an obstacle.
Like the reference, ``Q_c^μ`` and ``V_c^μ`` are estimated by rolling ``a`` then ``μ`` (resp.
``μ`` alone) through a model of the robot for ``horizon`` steps; the transform intervenes when
``A_c > eta``: ``μ`` acts instead of the learner, and the learner's episode ends there
(``terminated``) with ``intervention_reward``, the absorbing state of SAILR's surrogate MDP.

The model is a *nominal* one (SAILR "requires a robot model"): by default the recipes give it
the least-squares affine model of the random-input offline data (:class:`AffineModel`, exact for
the double integrator below its speed saturation), with no error bound, as in the reference.
"""
from __future__ import annotations

from collections.abc import Callable, Sequence

import torch
from tensordict import TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor

from torchrl_brsl.baselines._common import ActionFilter, check_dims, obstacle_tensors, point_clearance


def rollout_hits(model: Callable[[Tensor, Tensor], Tensor], backup: Callable[[Tensor], Tensor], state: Tensor,
                 first_action: Tensor | None, centers: Tensor, generators: Tensor, mask: Tensor, *, horizon: int,
                 position_dims: Sequence[int], shrink: float = 0.0) -> Tensor:
    """Whether the model trajectory (``first_action``, then ``backup``) meets an obstacle.

    The obstacles of the model are shrunk by ``shrink`` (a point counts as a hit when its
    clearance is below ``-shrink``), as the reference does with its walls. The current state
    itself is not checked: the cost is that of the steps to come.

    Args:
        model: ``(state [..., n], action [..., m]) -> next state [..., n]``.
        backup: ``state [..., n] -> action [..., m]``.
        state: ``[..., n]`` (float64).
        first_action: ``[..., m]`` or None (then ``backup`` from the start: ``V_c^μ``).
        centers, generators, mask: obstacles ``[..., K, d]``, ``[..., K, d, p]``, ``[..., K]``.
        horizon: model steps (the first action included).
        position_dims: position indices of the state.
        shrink: obstacle shrinkage in the model (>= 0).

    Returns:
        ``[...]`` bool.
    """
    dims = list(position_dims)
    hit = torch.zeros(state.shape[:-1], dtype=torch.bool, device=state.device)
    x = state.to(torch.float64)
    for t in range(horizon):
        action = first_action if (t == 0 and first_action is not None) else backup(x)
        x = model(x, action.to(torch.float64))
        hit |= (point_clearance(x[..., dims], centers, generators, mask) < -shrink).any(-1)
    return hit


class SAILRIntervener(ActionFilter):
    """SAILR's intervention rule as a TorchRL transform.

    Reads ``state_key [..., n]`` and ``obstacles_key``; computes
    ``A_c = Q_c^μ(s, a) - V_c^μ(s)`` in ``{-1, 0, 1}`` by :func:`rollout_hits`; where
    ``A_c > eta`` the executed ``action`` is ``backup(state)`` and, with
    ``terminate_on_intervention``, ``next["terminated"]`` and ``next["done"]`` are set and
    the reward is replaced by ``intervention_reward`` (the learner's absorbing state). Writes
    ``next[safe_action_key]`` and ``next[diagnostics_key]`` (``intervened``, ``compute_time``,
    ``advantage`` [1] float64).

    Args:
        model: the nominal model ``(state, action) -> next state`` (e.g. :class:`AffineModel`).
        backup: the backup policy ``μ``: ``state [..., n] -> action [..., m]``.
        horizon: model steps of each rollout (enough for ``μ`` to stop the robot).
        position_dims: position indices of the state.
        eta: intervention threshold (the reference: 0).
        shrink: obstacle shrinkage in the model, metres.
        intervention_reward: the learner's reward at an intervention (the lowest reward).
        terminate_on_intervention: end the episode at an intervention (training); False keeps
            the episode going with ``μ`` acting (evaluation of the learned policy).
        state_key, obstacles_key, action_key, safe_action_key, diagnostics_key, reward_key:
            TensorDict keys.

    Examples:
        >>> import envs
        >>> from torchrl.envs import TransformedEnv
        >>> from torchrl_brsl.baselines import AffineModel
        >>> info = envs.safety_info("point_boxes")
        >>> model = AffineModel(torch.eye(4), 0.1 * torch.eye(4, 2), torch.zeros(4))
        >>> sailr = SAILRIntervener(model, lambda s: info.braking_policy(s).double(), horizon=5, position_dims=(0, 1))
        >>> td = TransformedEnv(envs.make("point_boxes", seed=0), sailr).rollout(3)
        >>> td["next", "baseline", "advantage"].shape
        torch.Size([3, 1])
    """

    def __init__(self, model: Callable[[Tensor, Tensor], Tensor], backup: Callable[[Tensor], Tensor], *,
                 horizon: int, position_dims: Sequence[int], eta: float = 0.0, shrink: float = 0.0,
                 intervention_reward: float = 0.0, terminate_on_intervention: bool = True, **keys):
        super().__init__(**keys)
        if int(horizon) < 1:
            raise ValueError(f"`horizon` must be >= 1, got {horizon}")
        if shrink < 0:
            raise ValueError(f"`shrink` must be >= 0, got {shrink}")
        self.model, self.backup = model, backup
        self.horizon, self.eta, self.shrink = int(horizon), float(eta), float(shrink)
        self.position_dims = tuple(int(d) for d in position_dims)
        self.intervention_reward = float(intervention_reward)
        self.terminate_on_intervention = bool(terminate_on_intervention)

    def transform_observation_spec(self, observation_spec):
        from torchrl.data import Unbounded

        observation_spec = super().transform_observation_spec(observation_spec)
        batch = observation_spec.shape
        observation_spec[self.diagnostics_key]["advantage"] = Unbounded(shape=(*batch, 1), dtype=torch.float64,
                                                                        device=observation_spec.device)
        return observation_spec

    def _reset(self, tensordict, tensordict_reset):
        tensordict_reset = super()._reset(tensordict, tensordict_reset)
        tensordict_reset.set((self.diagnostics_key, "advantage"),
                             torch.zeros(*tensordict_reset.batch_size, 1, dtype=torch.float64,
                                         device=tensordict_reset.device))
        return tensordict_reset

    def advantage(self, tensordict: TensorDictBase) -> Tensor:
        """``A_c(s, a) [...]`` (float64, values in {-1, 0, 1}) of the step's proposal."""
        batch = tensordict.batch_size
        state = tensordict.get(self.state_key).to(torch.float64)
        check_dims("position_dims", self.position_dims, state.shape[-1])
        action = tensordict.get(self.action_key).to(torch.float64)
        centers, generators, mask = obstacle_tensors(tensordict, self.obstacles_key, batch)
        common = dict(horizon=self.horizon, position_dims=self.position_dims, shrink=self.shrink)
        q = rollout_hits(self.model, self.backup, state, action, centers, generators, mask, **common)
        v = rollout_hits(self.model, self.backup, state, None, centers, generators, mask, **common)
        return q.to(torch.float64) - v.to(torch.float64)

    def filter(self, tensordict):
        state = tensordict.get(self.state_key).to(torch.float64)
        action = tensordict.get(self.action_key)
        adv = self.advantage(tensordict)
        intervened = adv > self.eta
        executed = torch.where(intervened.unsqueeze(-1), self.backup(state).to(torch.float64), action.to(torch.float64))
        tensordict.set((self.diagnostics_key, "advantage"), adv.reshape(*tensordict.batch_size, 1))
        return executed, intervened, {}

    def _step(self, tensordict, next_tensordict):
        next_tensordict = super()._step(tensordict, next_tensordict)
        if self.terminate_on_intervention:
            intervened = tensordict.get((self.diagnostics_key, "intervened"))
            reward = next_tensordict.get(self.reward_key)
            next_tensordict.set(self.reward_key, torch.where(intervened.reshape(reward.shape),
                                                             torch.full_like(reward, self.intervention_reward), reward))
            for key in ("terminated", "done"):
                flag = next_tensordict.get(key)
                next_tensordict.set(key, flag | intervened.reshape(flag.shape))
        return next_tensordict
