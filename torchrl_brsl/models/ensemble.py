"""Probabilistic ensemble of Gaussian MLPs (PETS, Chua et al. 2018) as a transition model.

Shapes below use ``E`` for the ensemble size, ``N``/``B`` for samples, ``d`` for the
observation dimension, ``m`` for the action dimension and ``o = d (+ 1)`` for the predicted
targets (observation delta, then the reward when it is predicted).
"""
from __future__ import annotations

import math
from typing import Sequence

import torch
import torch.nn.functional as F
from tensordict.nn import TensorDictModule
from tensordict.utils import NestedKey
from torch import Tensor, nn

from torchrl_brsl.models.normalizer import Normalizer


class EnsembleLinear(nn.Module):
    """``E`` independent linear layers evaluated in one batched matrix product.

    ``weight`` is ``[E, in, out]`` and ``bias`` ``[E, 1, out]``; member ``e`` maps
    ``x[e] [N, in]`` to ``x[e] @ weight[e] + bias[e]``. Initialisation as in PETS: weights from
    a normal with std ``1 / (2 sqrt(in))`` truncated at two standard deviations, zero biases,
    drawn independently per member (so members differ from the start).

    Args:
        ensemble_size: ``E``.
        in_features, out_features: layer widths.

    Examples:
        >>> layer = EnsembleLinear(5, 3, 4)
        >>> layer(torch.randn(5, 10, 3)).shape
        torch.Size([5, 10, 4])
        >>> layer(torch.randn(10, 3)).shape  # one input shared by every member
        torch.Size([5, 10, 4])
    """

    def __init__(self, ensemble_size: int, in_features: int, out_features: int, *, device=None, dtype=None):
        super().__init__()
        self.ensemble_size, self.in_features, self.out_features = int(ensemble_size), int(in_features), int(out_features)
        factory = {"device": device, "dtype": dtype}
        self.weight = nn.Parameter(torch.empty(self.ensemble_size, self.in_features, self.out_features, **factory))
        self.bias = nn.Parameter(torch.empty(self.ensemble_size, 1, self.out_features, **factory))
        self.reset_parameters()

    @torch.no_grad()
    def reset_parameters(self) -> None:
        std = 1.0 / (2.0 * math.sqrt(self.in_features))
        nn.init.trunc_normal_(self.weight, std=std, a=-2 * std, b=2 * std)
        self.bias.zero_()

    def forward(self, x: Tensor) -> Tensor:
        """``x [E, N, in]`` (or ``[N, in]``, shared by all members) -> ``[E, N, out]``."""
        if x.dim() == 2:
            x = x.expand(self.ensemble_size, *x.shape)
        return torch.baddbmm(self.bias, x, self.weight)

    def extra_repr(self) -> str:
        return f"ensemble_size={self.ensemble_size}, in_features={self.in_features}, out_features={self.out_features}"


class ProbabilisticEnsemble(nn.Module):
    """Ensemble of ``E`` Gaussian MLPs predicting ``(next observation - observation, reward)``.

    Each member maps the normalised input ``[observation, action]`` through ``num_layers``
    linear layers (``d + m -> H -> ... -> H -> 2 o``, LeakyReLU with slope 0.01 between them;
    the paper's setup is 4 layers with ``H = 200``) to the mean and log-variance of a diagonal
    Gaussian over the normalised target ``o = [delta observation, reward]``. All members run in
    one batched call (:class:`EnsembleLinear`).

    Log-variance bounds (PETS): the raw log-variance ``l`` is soft-clamped by learnable
    ``max_log_var`` / ``min_log_var`` (one per target dim, shared by the members)::

        l <- max_log_var - softplus(max_log_var - l)
        l <- min_log_var + softplus(l - min_log_var)

    so every predicted log-variance lies in
    ``[min_log_var, max_log_var + softplus(min_log_var - max_log_var)]`` (the upper slack is
    ``< 3e-5`` at the default bounds). :meth:`log_var_bound_penalty` is the small regulariser
    ``sum(max_log_var) - sum(min_log_var)`` that :class:`WorldModelLoss` adds so the bounds
    tighten around the data instead of drifting apart.

    Normalisation: ``input_normalizer`` (over ``[observation, action]``) and
    ``target_normalizer`` (over the targets) are :class:`Normalizer` buffers, fitted from data
    with :meth:`fit_normalizers` (``train_world_model`` does this from the replay buffer).
    Predictions in the original units come from :meth:`forward` and :meth:`propagate`.

    Args:
        observation_dim: ``d``.
        action_dim: ``m``.
        ensemble_size: ``E``.
        hidden_size: ``H``.
        num_layers: number of linear layers (at least 2).
        predict_reward: also model the reward (``o = d + 1``); otherwise ``o = d``.
        negative_slope: LeakyReLU slope.
        init_max_log_var, init_min_log_var: initial log-variance bounds (normalised units).
        device, dtype: of parameters and buffers.

    Examples:
        >>> model = ProbabilisticEnsemble(observation_dim=4, action_dim=2, ensemble_size=5)
        >>> obs, act = torch.randn(8, 4), torch.randn(8, 2)
        >>> obs_loc, obs_scale, rew_loc, rew_scale = model(obs, act)  # every member
        >>> obs_loc.shape, rew_scale.shape
        (torch.Size([8, 5, 4]), torch.Size([8, 5, 1]))
        >>> next_obs, reward = model.propagate(obs, act, torch.randint(5, (8,)))  # one sample each
        >>> next_obs.shape, reward.shape
        (torch.Size([8, 4]), torch.Size([8, 1]))
    """

    def __init__(self, observation_dim: int, action_dim: int, *, ensemble_size: int = 5, hidden_size: int = 200,
                 num_layers: int = 4, predict_reward: bool = True, negative_slope: float = 0.01,
                 init_max_log_var: float = 0.5, init_min_log_var: float = -10.0, device=None, dtype=None):
        super().__init__()
        if int(num_layers) < 2:
            raise ValueError(f"`num_layers` must be at least 2, got {num_layers}")
        if int(ensemble_size) < 1:
            raise ValueError(f"`ensemble_size` must be positive, got {ensemble_size}")
        if not init_min_log_var < init_max_log_var:
            raise ValueError("`init_min_log_var` must be below `init_max_log_var`")
        self.observation_dim, self.action_dim = int(observation_dim), int(action_dim)
        self.ensemble_size, self.hidden_size, self.num_layers = int(ensemble_size), int(hidden_size), int(num_layers)
        self.predict_reward = bool(predict_reward)
        self.negative_slope = float(negative_slope)
        self.input_dim = self.observation_dim + self.action_dim
        self.output_dim = self.observation_dim + int(self.predict_reward)
        factory = {"device": device, "dtype": dtype}
        widths = [self.input_dim] + [self.hidden_size] * (self.num_layers - 1) + [2 * self.output_dim]
        self.layers = nn.ModuleList(EnsembleLinear(self.ensemble_size, a, b, **factory)
                                    for a, b in zip(widths[:-1], widths[1:]))
        self.max_log_var = nn.Parameter(torch.full((self.output_dim,), float(init_max_log_var), **factory))
        self.min_log_var = nn.Parameter(torch.full((self.output_dim,), float(init_min_log_var), **factory))
        self.input_normalizer = Normalizer(self.input_dim, **factory)
        self.target_normalizer = Normalizer(self.output_dim, **factory)

    # ----------------------------------------------------------------------------- network
    def network(self, x: Tensor) -> tuple[Tensor, Tensor]:
        """Raw ensemble call in normalised units.

        Args:
            x: normalised inputs ``[E, N, d + m]`` (member ``e`` reads ``x[e]``) or ``[N, d + m]``
                (every member reads the same rows).

        Returns:
            ``(mean, log_var)``, each ``[E, N, o]``, in normalised target units, ``log_var``
            soft-clamped to the learnable bounds.
        """
        return self._heads(self._trunk(x))

    def _trunk(self, x: Tensor) -> Tensor:
        """The layers: ``x [E, N, d + m]`` or ``[N, d + m]`` -> raw ``[E, N, 2 o]``."""
        h = x
        for layer in self.layers[:-1]:
            h = F.leaky_relu(layer(h), self.negative_slope)
        return self.layers[-1](h)

    def _heads(self, raw: Tensor) -> tuple[Tensor, Tensor]:
        """Raw ``[..., 2 o]`` -> ``(mean, soft-clamped log_var)``, each ``[..., o]``."""
        mean, log_var = raw.chunk(2, dim=-1)
        log_var = self.max_log_var - F.softplus(self.max_log_var - log_var)
        log_var = self.min_log_var + F.softplus(log_var - self.min_log_var)
        return mean, log_var

    def log_var_bound_penalty(self) -> Tensor:
        """``sum(max_log_var) - sum(min_log_var)`` (scalar), the PETS bound regulariser."""
        return self.max_log_var.sum() - self.min_log_var.sum()

    def _model_input(self, observation: Tensor, action: Tensor) -> Tensor:
        dtype = self.max_log_var.dtype
        if observation.shape[-1] != self.observation_dim:
            raise ValueError(f"observation has {observation.shape[-1]} dims, the model expects {self.observation_dim}")
        if action.shape[-1] != self.action_dim:
            raise ValueError(f"action has {action.shape[-1]} dims, the model expects {self.action_dim}")
        if observation.shape[:-1] != action.shape[:-1]:
            raise ValueError(f"observation {tuple(observation.shape)} and action {tuple(action.shape)} batch "
                             "shapes differ")
        x = torch.cat((observation.to(dtype), action.to(dtype)), dim=-1)
        return self.input_normalizer.normalize(x)

    def normalized_prediction(self, observation: Tensor, action: Tensor) -> tuple[Tensor, Tensor]:
        """Per-member ``(mean, log_var)`` of the normalised targets.

        Args:
            observation: ``[E, N, d]`` (one batch per member) or ``[N, d]`` (shared).
            action: ``[E, N, m]`` or ``[N, m]``, like ``observation``.

        Returns:
            ``(mean, log_var)``, each ``[E, N, o]``.
        """
        return self.network(self._model_input(observation, action))

    def targets(self, observation: Tensor, next_observation: Tensor, reward: Tensor | None = None) -> Tensor:
        """Regression targets ``[..., o]``: ``next_observation - observation`` (and ``reward [..., 1]``)."""
        dtype = self.max_log_var.dtype
        delta = next_observation.to(dtype) - observation.to(dtype)
        if not self.predict_reward:
            return delta
        if reward is None:
            raise ValueError("this model predicts the reward: pass `reward [..., 1]`")
        if reward.shape[-1:] != (1,) or reward.dim() != delta.dim():
            reward = reward.reshape(*delta.shape[:-1], 1)
        return torch.cat((delta, reward.to(dtype)), dim=-1)

    @torch.no_grad()
    def fit_normalizers(self, observation: Tensor, action: Tensor, next_observation: Tensor,
                        reward: Tensor | None = None) -> None:
        """Fits both normalisers to a data set (``[..., d]``, ``[..., m]``, ``[..., d]``, ``[..., 1]``)."""
        self.input_normalizer.fit(torch.cat((observation.to(self.max_log_var.dtype),
                                             action.to(self.max_log_var.dtype)), dim=-1))
        self.target_normalizer.fit(self.targets(observation, next_observation, reward))

    @torch.no_grad()
    def update_normalizers(self, observation: Tensor, action: Tensor, next_observation: Tensor,
                           reward: Tensor | None = None) -> None:
        """Merges a batch into the running normaliser statistics (see :meth:`Normalizer.update`)."""
        self.input_normalizer.update(torch.cat((observation.to(self.max_log_var.dtype),
                                                action.to(self.max_log_var.dtype)), dim=-1))
        self.target_normalizer.update(self.targets(observation, next_observation, reward))

    # ----------------------------------------------------------------------------- predictions
    def _split(self, loc: Tensor, scale: Tensor, observation: Tensor) -> tuple[Tensor, ...]:
        d = self.observation_dim
        obs_loc = loc[..., :d] + observation.to(loc.dtype)
        out = (obs_loc, scale[..., :d])
        if self.predict_reward:
            out = out + (loc[..., d:], scale[..., d:])
        return out

    def forward(self, observation: Tensor, action: Tensor) -> tuple[Tensor, ...]:
        """Every member's Gaussian over the next observation (and reward), in original units.

        Args:
            observation: ``[*batch, d]`` (``batch`` may be empty).
            action: ``[*batch, m]``.

        Returns:
            ``(observation_loc, observation_scale)`` ``[*batch, E, d]`` and, when the reward is
            predicted, ``(reward_loc, reward_scale)`` ``[*batch, E, 1]``; ``*_scale`` are standard
            deviations. The member dim comes after the batch dims so the outputs fit a
            TensorDict with batch size ``batch``.
        """
        batch = observation.shape[:-1]
        x = self._model_input(observation, action).reshape(-1, self.input_dim)
        mean, log_var = self.network(x)  # [E, N, o]
        loc = self.target_normalizer.denormalize(mean)
        scale = (0.5 * log_var).exp() * self.target_normalizer.std
        loc = loc.transpose(0, 1).reshape(*batch, self.ensemble_size, self.output_dim)
        scale = scale.transpose(0, 1).reshape(*batch, self.ensemble_size, self.output_dim)
        return self._split(loc, scale, observation.unsqueeze(-2))

    def propagate(self, observation: Tensor, action: Tensor, member: Tensor, *, sample: bool = True,
                  generator: torch.Generator | None = None) -> tuple[Tensor, Tensor | None]:
        """One trajectory-sampling step: row ``i`` moves with member ``member[i]``.

        ``next = observation + delta`` with ``delta`` drawn from the member's Gaussian by
        reparameterisation (``mean + std * eps``), so the result is differentiable in
        ``observation``, ``action`` and the model parameters for a fixed noise draw. TS1 and
        TS-infinity (Chua et al. 2018) differ only in how the caller picks ``member`` at each
        step (resampled every step vs fixed per trajectory); see
        :class:`~torchrl_brsl.planning.RolloutPlanner`.

        All ``E`` members are evaluated on every row and the chosen ones gathered: one batched
        call, cheaper on a CPU than gathering per-row weights.

        Args:
            observation: ``[B, d]``.
            action: ``[B, m]``.
            member: ``[B]`` member index per row (int64 in ``[0, E)``).
            sample: draw from the Gaussian; ``False`` returns the member's mean.
            generator: RNG for the noise (default: the global one).

        Returns:
            ``(next_observation [B, d], reward [B, 1])`` in ``observation``'s dtype; ``reward``
            is ``None`` when the model does not predict it.
        """
        if observation.dim() != 2:
            raise ValueError(f"`observation` must be [B, d], got {tuple(observation.shape)}")
        n = observation.shape[0]
        member = torch.as_tensor(member, device=observation.device).long().reshape(-1).expand(n)
        raw = self._trunk(self._model_input(observation, action))  # [E, B, 2 o]
        mean, log_var = self._heads(raw[member, torch.arange(n, device=observation.device)])  # [B, o]
        if sample:
            eps = torch.randn(mean.shape, generator=generator, device=mean.device, dtype=mean.dtype)
            mean = mean + (0.5 * log_var).exp() * eps
        target = self.target_normalizer.denormalize(mean)
        next_observation = (observation.to(target.dtype) + target[:, :self.observation_dim]).to(observation.dtype)
        reward = target[:, self.observation_dim:].to(observation.dtype) if self.predict_reward else None
        return next_observation, reward

    def extra_repr(self) -> str:
        return (f"observation_dim={self.observation_dim}, action_dim={self.action_dim}, "
                f"ensemble_size={self.ensemble_size}, predict_reward={self.predict_reward}")


class WorldModel(TensorDictModule):
    """A :class:`ProbabilisticEnsemble` as a :class:`~tensordict.nn.TensorDictModule`.

    Reads the observation and action and writes every member's predictive Gaussian
    ``[*batch, E, d]`` (and ``[*batch, E, 1]`` for the reward) under ``out_keys``.
    The underlying ensemble is ``world_model.ensemble`` (also ``world_model.module``);
    :class:`WorldModelLoss` and :class:`~torchrl_brsl.planning.RolloutPlanner` accept either.

    Args:
        ensemble: the :class:`ProbabilisticEnsemble`.
        in_keys: ``(observation_key, action_key)``.
        out_keys: keys for ``observation_loc, observation_scale`` (and ``reward_loc,
            reward_scale`` when the ensemble predicts the reward). Default:
            ``("next", "observation_loc")``, ``("next", "observation_scale")``,
            ``("next", "reward_loc")``, ``("next", "reward_scale")``.

    Examples:
        >>> from tensordict import TensorDict
        >>> world_model = WorldModel(ProbabilisticEnsemble(4, 2, ensemble_size=3))
        >>> td = TensorDict(observation=torch.randn(8, 4), action=torch.randn(8, 2), batch_size=[8])
        >>> td = world_model(td)
        >>> td["next", "observation_loc"].shape, td["next", "reward_scale"].shape
        (torch.Size([8, 3, 4]), torch.Size([8, 3, 1]))
    """

    def __init__(self, ensemble: ProbabilisticEnsemble, *,
                 in_keys: Sequence[NestedKey] = ("observation", "action"),
                 out_keys: Sequence[NestedKey] | None = None):
        if not isinstance(ensemble, ProbabilisticEnsemble):
            raise ValueError(f"`ensemble` must be a ProbabilisticEnsemble, got {type(ensemble).__name__}")
        if out_keys is None:
            out_keys = [("next", "observation_loc"), ("next", "observation_scale")]
            if ensemble.predict_reward:
                out_keys += [("next", "reward_loc"), ("next", "reward_scale")]
        out_keys = list(out_keys)
        expected = 4 if ensemble.predict_reward else 2
        if len(out_keys) != expected:
            raise ValueError(f"expected {expected} out_keys, got {len(out_keys)}")
        if len(in_keys) != 2:
            raise ValueError(f"expected in_keys (observation, action), got {in_keys}")
        super().__init__(ensemble, in_keys=list(in_keys), out_keys=out_keys)

    @property
    def ensemble(self) -> ProbabilisticEnsemble:
        """The wrapped :class:`ProbabilisticEnsemble`."""
        return self.module


def as_ensemble(world_model) -> ProbabilisticEnsemble:
    """The :class:`ProbabilisticEnsemble` behind ``world_model`` (itself or a TensorDictModule's ``module``)."""
    if isinstance(world_model, ProbabilisticEnsemble):
        return world_model
    module = getattr(world_model, "module", None)
    if isinstance(module, ProbabilisticEnsemble):
        return module
    raise ValueError(f"expected a ProbabilisticEnsemble or a TensorDictModule wrapping one, "
                     f"got {type(world_model).__name__}")
