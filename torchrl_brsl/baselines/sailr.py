"""SAILR: advantage-based intervention with a backup policy.

Wagener, Boots, Cheng, "Safe reinforcement learning using advantage-based intervention",
ICML 2021; reference code ``nolanwagener/safe_rl`` (the point-robot intervener).

A backup policy ``μ`` (the task's braking policy, e.g. ``a = clip(-v / dt)`` for the
double integrator, zero command for velocity-commanded robots) and the cost advantage
``A_c(s, a) = Q_c^μ(s, a) - V_c^μ(s)``, with cost 1 at a step that meets an obstacle. Like the
reference (``PointIntervenerRollout``), ``Q_c^μ`` and ``V_c^μ`` are the discounted costs of rolling
``a`` then ``μ`` (resp. ``μ`` alone) through a model of the robot until it stops or hits
(:func:`rollout_cost`); the transform intervenes when
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
from torch import Tensor

from torchrl_brsl.baselines._common import ActionFilter, check_dims, obstacle_tensors, point_clearance


def rollout_cost(model: Callable[[Tensor, Tensor], Tensor], backup: Callable[[Tensor], Tensor], state: Tensor,
                 first_action: Tensor | None, centers: Tensor, generators: Tensor, mask: Tensor, *, horizon: int,
                 position_dims: Sequence[int], velocity_dims: Sequence[int], stop_tolerance: float = 1e-3,
                 gamma: float = 0.99, margin: float = 0.0, cost_smoothing: float = 0.0) -> Tensor:
    """Discounted cost of the model trajectory (``first_action``, then ``backup``), as the reference.

    The rollout from ``state`` ends at the first hit, once the robot is stopped
    (``|velocity| <= stop_tolerance``) or after ``horizon`` steps. A hit is a position within
    ``margin`` of an obstacle (the model's safe set shrunk, like the reference's slightly shrunk
    walls). The cost of step ``t >= 1`` is 1 at a hit, else
    ``max(0, 1 - (clearance - margin) / cost_smoothing)`` with ``cost_smoothing > 0`` (the
    reference's graded cost), or 0; the return is ``sum_t gamma^t c_t``, so a hit that comes
    sooner costs more and an action that brings an unavoidable crash closer has a positive
    advantage. With the 0/1 cost a robot that the process noise pushed into the model's unsafe
    set has ``A_c = 0`` whatever it does (both rollouts hit at once) and may be driven on into
    the obstacle; with the graded cost, moving closer always costs more than braking.

    Args:
        model: ``(state [..., n], action [..., m]) -> next state [..., n]``.
        backup: ``state [..., n] -> action [..., m]``.
        state: ``[..., n]`` (float64).
        first_action: ``[..., m]`` or None (then ``backup`` from the start: ``V_c^μ``).
        centers, generators, mask: obstacles ``[..., K, d]``, ``[..., K, d, p]``, ``[..., K]``.
        horizon: the most model steps (the first action included).
        position_dims: position indices of the state.
        velocity_dims: velocity indices of the state (for the stop test).
        stop_tolerance: speed per velocity dim below which the robot counts as stopped.
        gamma: discount.
        margin: the model's safe set is shrunk by this distance (>= 0; see above).
        cost_smoothing: width of the cost ramp outside the shrunk safe set (0: the 0/1 cost).

    Returns:
        ``[...]`` float64.
    """
    dims, vdims = list(position_dims), list(velocity_dims)
    x = state.to(torch.float64)
    total = torch.zeros(x.shape[:-1], dtype=torch.float64, device=x.device)
    alive = torch.ones(x.shape[:-1], dtype=torch.bool, device=x.device)
    for t in range(1, horizon + 1):
        action = first_action if (t == 1 and first_action is not None) else backup(x)
        x = model(x, action.to(torch.float64))
        clear = point_clearance(x[..., dims], centers, generators, mask).amin(-1) - margin
        hit = clear <= 0
        cost = hit.to(torch.float64)
        if cost_smoothing > 0:
            cost = torch.where(hit, 1.0, (1 - clear / cost_smoothing).clamp_min(0.0))
        total = total + torch.where(alive, gamma ** t * cost, 0.0)
        alive = alive & ~hit & (x[..., vdims].abs().amax(-1) > stop_tolerance)
    return total


class SAILRIntervener(ActionFilter):
    """SAILR's intervention rule as a TorchRL transform.

    Reads ``state_key [..., n]`` and ``obstacles_key``; computes
    ``A_c = Q_c^μ(s, a) - V_c^μ(s)`` by :func:`rollout_cost`; where
    ``A_c > eta`` the executed ``action`` is ``backup(state)`` and, with
    ``terminate_on_intervention``, ``next["terminated"]`` and ``next["done"]`` are set and
    the reward is replaced by ``intervention_reward`` (the learner's absorbing state). Writes
    ``next[safe_action_key]`` and ``next[diagnostics_key]`` (``intervened``, ``compute_time``,
    ``advantage`` [1] float64).

    Args:
        model: the nominal model ``(state, action) -> next state`` (e.g. :class:`AffineModel`).
        backup: the backup policy ``μ``: ``state [..., n] -> action [..., m]``.
        horizon: the most model steps of each rollout (enough for ``μ`` to stop the robot).
        position_dims: position indices of the state.
        velocity_dims: velocity indices of the state (the rollouts end once it is stopped).
        eta: intervention threshold (the issue's setting: 0; the reference code: 0.01).
        gamma: discount of the cost.
        stop_tolerance: the robot counts as stopped below this speed per velocity dim.
        margin: the model's safe set is shrunk by this distance, metres (the robot then stops
            short of the obstacles, whatever the noise adds).
        cost_smoothing: see :func:`rollout_cost`.
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
        >>> sailr = SAILRIntervener(model, lambda s: info.braking_policy(s).double(), horizon=5, position_dims=(0, 1),
        ...                         velocity_dims=(2, 3))
        >>> td = TransformedEnv(envs.make("point_boxes", seed=0), sailr).rollout(3)
        >>> td["next", "baseline", "advantage"].shape
        torch.Size([3, 1])
    """

    def __init__(self, model: Callable[[Tensor, Tensor], Tensor], backup: Callable[[Tensor], Tensor], *,
                 horizon: int, position_dims: Sequence[int], velocity_dims: Sequence[int], eta: float = 0.0,
                 gamma: float = 0.99, stop_tolerance: float = 1e-3, margin: float = 0.0, cost_smoothing: float = 0.0,
                 intervention_reward: float = 0.0, terminate_on_intervention: bool = True, **keys):
        super().__init__(**keys)
        if int(horizon) < 1:
            raise ValueError(f"`horizon` must be >= 1, got {horizon}")
        if margin < 0 or cost_smoothing < 0:
            raise ValueError(f"`margin` and `cost_smoothing` must be >= 0, got {margin}, {cost_smoothing}")
        if not 0 < gamma <= 1:
            raise ValueError(f"`gamma` must be in (0, 1], got {gamma}")
        self.model, self.backup = model, backup
        self.horizon, self.eta, self.margin = int(horizon), float(eta), float(margin)
        self.position_dims = tuple(int(d) for d in position_dims)
        self.velocity_dims = tuple(int(d) for d in velocity_dims)
        self.gamma, self.stop_tolerance, self.cost_smoothing = float(gamma), float(stop_tolerance), float(cost_smoothing)
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
        """``A_c(s, a) [...]`` (float64) of the step's proposal."""
        batch = tensordict.batch_size
        state = tensordict.get(self.state_key).to(torch.float64)
        check_dims("position_dims", self.position_dims, state.shape[-1])
        check_dims("velocity_dims", self.velocity_dims, state.shape[-1])
        action = tensordict.get(self.action_key).to(torch.float64)
        centers, generators, mask = obstacle_tensors(tensordict, self.obstacles_key, batch)
        common = dict(horizon=self.horizon, position_dims=self.position_dims, velocity_dims=self.velocity_dims,
                      stop_tolerance=self.stop_tolerance, gamma=self.gamma, margin=self.margin,
                      cost_smoothing=self.cost_smoothing)
        q = rollout_cost(self.model, self.backup, state, action, centers, generators, mask, **common)
        v = rollout_cost(self.model, self.backup, state, None, centers, generators, mask, **common)
        return q - v

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
