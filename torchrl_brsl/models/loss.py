"""``WorldModelLoss`` (Gaussian NLL of the ensemble) and the ``train_world_model`` helper."""
from __future__ import annotations

from dataclasses import dataclass

import torch
from tensordict import TensorDict, TensorDictBase
from tensordict.utils import NestedKey
from torch import Tensor
from torchrl.objectives import LossModule

from torchrl_brsl.models.ensemble import ProbabilisticEnsemble, as_ensemble


class WorldModelLoss(LossModule):
    """Gaussian negative log-likelihood of a :class:`ProbabilisticEnsemble` (PETS).

    Reads transitions ``observation [*, d]``, ``action [*, m]``, ``("next", observation)``
    ``[*, d]`` and ``("next", reward)`` ``[*, 1]`` (the layout of a TorchRL collector's output
    and of replay-buffer samples) and returns::

        TensorDict(loss_world_model=<scalar with grad>, nll=<detached>, mse=<detached>)

    With ``mu_e, log_var_e`` member ``e``'s prediction of the normalised target
    ``z = target_normalizer((next_obs - obs, reward))``::

        nll_e = mean_{n, k} 0.5 * ((mu_e - z)^2 * exp(-log_var_e) + log_var_e)
        loss_world_model = sum_e nll_e + log_var_bound_coef * (sum max_log_var - sum min_log_var)

    (``nll_e`` omits the constant ``0.5 log 2 pi``; members are summed, as in PETS, so each
    member's gradient does not depend on ``E``.) ``nll`` is the mean of ``nll_e`` over the
    members and ``mse`` the mean squared error of the predicted means, both in normalised units.

    Which samples each member sees:

    - a batch ``[E, N]`` (e.g. ``buffer.sample(E * N).reshape(E, N)``, what
      :func:`train_world_model` does): member ``e`` is trained on row ``e``, independent
      minibatches per member;
    - any other batch shape is flattened to ``[N]``; with ``bootstrap=True`` (default) each
      member gets its own resample of those ``N`` transitions with replacement, otherwise all
      members see the same ``N``.

    Keys are set as in other TorchRL losses: ``loss.set_keys(observation=..., action=...,
    reward=...)``; the next observation and the reward are read under ``"next"``.

    Args:
        world_model: a :class:`ProbabilisticEnsemble` or a :class:`WorldModel` wrapping one.
        bootstrap: resample a flat batch per member (see above).
        log_var_bound_coef: weight of the log-variance bound regulariser (PETS: 0.01).

    Examples:
        >>> from torchrl.data import LazyTensorStorage, ReplayBuffer
        >>> model = ProbabilisticEnsemble(3, 1, ensemble_size=2, hidden_size=16)
        >>> buffer = ReplayBuffer(storage=LazyTensorStorage(100))
        >>> _ = buffer.extend(TensorDict(observation=torch.randn(100, 3), action=torch.randn(100, 1),
        ...     next=TensorDict(observation=torch.randn(100, 3), reward=torch.randn(100, 1), batch_size=[100]),
        ...     batch_size=[100]))
        >>> loss_module = WorldModelLoss(model)
        >>> losses = loss_module(buffer.sample(32))
        >>> losses["loss_world_model"].backward()
        >>> sorted(losses.keys())
        ['loss_world_model', 'mse', 'nll']
    """

    @dataclass
    class _AcceptedKeys:
        """Configurable TensorDict keys.

        Attributes:
            observation: the observation, also read under ``"next"``. Default ``"observation"``.
            action: the action. Default ``"action"``.
            reward: read as ``("next", reward)``. Default ``"reward"``.
        """

        observation: NestedKey = "observation"
        action: NestedKey = "action"
        reward: NestedKey = "reward"

    tensor_keys: _AcceptedKeys
    default_keys = _AcceptedKeys

    def __init__(self, world_model, *, bootstrap: bool = True, log_var_bound_coef: float = 0.01):
        super().__init__()
        self.world_model = world_model
        self.__dict__["ensemble"] = as_ensemble(world_model)
        self.bootstrap = bool(bootstrap)
        self.log_var_bound_coef = float(log_var_bound_coef)

    def _forward_value_estimator_keys(self, **kwargs) -> None:
        pass

    @property
    def in_keys(self):
        keys = [self.tensor_keys.observation, self.tensor_keys.action, ("next", self.tensor_keys.observation)]
        if self.ensemble.predict_reward:
            keys.append(("next", self.tensor_keys.reward))
        return keys

    @property
    def out_keys(self):
        return ["loss_world_model", "nll", "mse"]

    def _read(self, tensordict: TensorDictBase) -> tuple[Tensor, ...]:
        keys = self.tensor_keys
        needed = [keys.observation, keys.action, ("next", keys.observation)]
        if self.ensemble.predict_reward:
            needed.append(("next", keys.reward))
        values = []
        for key in needed:
            value = tensordict.get(key, None)
            if value is None:
                raise KeyError(f"WorldModelLoss: the TensorDict has no {key!r} (keys are set with `set_keys`)")
            values.append(value)
        if len(values) == 3:
            values.append(None)
        return tuple(values)

    def _member_batches(self, tensordict: TensorDictBase) -> tuple[Tensor, Tensor, Tensor]:
        """``(observation [E, N, d], action [E, N, m], normalised target [E, N, o])``."""
        model = self.ensemble
        E = model.ensemble_size
        obs, action, next_obs, reward = self._read(tensordict)
        per_member = tensordict.batch_dims == 2 and tensordict.batch_size[0] == E
        shape = tensordict.batch_size if per_member else torch.Size([tensordict.batch_size.numel()])
        obs = obs.reshape(*shape, model.observation_dim)
        action = action.reshape(*shape, model.action_dim)
        next_obs = next_obs.reshape(*shape, model.observation_dim)
        if reward is not None:
            reward = reward.reshape(*shape, 1)
        target = model.target_normalizer.normalize(model.targets(obs, next_obs, reward))
        if not per_member:
            n = shape[0]
            if n == 0:
                raise ValueError("WorldModelLoss got an empty batch")
            if self.bootstrap:
                index = torch.randint(n, (E, n), device=obs.device)
                obs, action, target = obs[index], action[index], target[index]
            else:
                obs, action, target = (x.expand(E, *x.shape) for x in (obs, action, target))
        return obs, action, target

    def forward(self, tensordict: TensorDictBase) -> TensorDict:
        """Loss of a batch of transitions ``tensordict`` (see the class docstring)."""
        model = self.ensemble
        obs, action, target = self._member_batches(tensordict)
        mean, log_var = model.normalized_prediction(obs, action)  # [E, N, o]
        sq_err = (mean - target).square()
        nll = 0.5 * (sq_err * (-log_var).exp() + log_var)
        nll_member = nll.mean(dim=(1, 2))  # [E]
        loss = nll_member.sum() + self.log_var_bound_coef * model.log_var_bound_penalty()
        return TensorDict(loss_world_model=loss, nll=nll_member.mean().detach(),
                          mse=sq_err.mean().detach(), batch_size=[])


def _all_transitions(replay_buffer) -> TensorDictBase:
    data = replay_buffer[:]
    if not isinstance(data, TensorDictBase):
        raise ValueError(f"the replay buffer must store TensorDicts, got {type(data).__name__}")
    return data.reshape(-1)


def train_world_model(model, loss_module: WorldModelLoss, replay_buffer, n_steps: int, optimizer: torch.optim.Optimizer,
                      *, batch_size: int = 256, fit_normalizers: bool = True, independent_batches: bool = True,
                      max_grad_norm: float | None = None) -> Tensor:
    """Trains the world model for ``n_steps`` gradient steps on samples of ``replay_buffer``.

    Meant to be called once per collected batch (paper Algorithm 1, line "train ... the
    environment model using minibatches from B"):

    1. with ``fit_normalizers`` the input / target normalisers are refitted on everything in
       the buffer (the normalised inputs shift a little each call, as in PETS);
    2. each step samples ``E * batch_size`` transitions and gives each member its own
       ``batch_size`` of them (``independent_batches``; otherwise one ``batch_size`` sample,
       resampled per member if ``loss_module.bootstrap``), then takes one optimiser step
       on ``loss_world_model``.

    Args:
        model: the :class:`ProbabilisticEnsemble` (or :class:`WorldModel`) that
            ``loss_module`` trains.
        loss_module: a :class:`WorldModelLoss` of ``model``.
        replay_buffer: a TorchRL replay buffer of transitions (keys as ``loss_module`` reads
            them), e.g. ``ReplayBuffer(storage=LazyTensorStorage(n))``.
        n_steps: number of gradient steps.
        optimizer: over ``model.parameters()`` (e.g. ``Adam(lr=1e-3)``; PETS also uses a small
            weight decay).
        batch_size: transitions per member per step.
        fit_normalizers: refit the normalisers on the whole buffer first.
        independent_batches: independent minibatches per member (see above).
        max_grad_norm: clip the gradient norm when given.

    Returns:
        ``loss_world_model`` per step, ``[n_steps]`` (detached).

    Examples:
        >>> from torchrl.data import LazyTensorStorage, ReplayBuffer
        >>> model = ProbabilisticEnsemble(2, 1, ensemble_size=3, hidden_size=32)
        >>> obs, act = torch.randn(500, 2), torch.randn(500, 1)
        >>> nxt = obs + 0.1 * act + 0.01 * torch.randn(500, 2)
        >>> buffer = ReplayBuffer(storage=LazyTensorStorage(1000))
        >>> _ = buffer.extend(TensorDict(observation=obs, action=act,
        ...     next=TensorDict(observation=nxt, reward=obs[:, :1], batch_size=[500]), batch_size=[500]))
        >>> loss_module = WorldModelLoss(model)
        >>> losses = train_world_model(model, loss_module, buffer, 50, torch.optim.Adam(model.parameters(), 1e-3))
        >>> bool(losses[-10:].mean() < losses[:10].mean())
        True
    """
    ensemble = as_ensemble(model)
    if not isinstance(loss_module, WorldModelLoss):
        raise ValueError(f"`loss_module` must be a WorldModelLoss, got {type(loss_module).__name__}")
    if loss_module.ensemble is not ensemble:
        raise ValueError("`loss_module` does not train `model`")
    if len(replay_buffer) == 0:
        raise ValueError("the replay buffer is empty")
    if fit_normalizers:
        data = _all_transitions(replay_buffer)
        obs, action, next_obs, reward = loss_module._read(data)
        ensemble.fit_normalizers(obs, action, next_obs, reward)
    E = ensemble.ensemble_size
    losses = torch.empty(int(n_steps))
    was_training = ensemble.training
    ensemble.train()
    params = [p for group in optimizer.param_groups for p in group["params"]]
    for step in range(int(n_steps)):
        if independent_batches:
            batch = replay_buffer.sample(E * batch_size).reshape(E, batch_size)
        else:
            batch = replay_buffer.sample(batch_size)
        loss = loss_module(batch)["loss_world_model"]
        optimizer.zero_grad(set_to_none=True)
        loss.backward()
        if max_grad_norm is not None:
            torch.nn.utils.clip_grad_norm_(params, max_grad_norm)
        optimizer.step()
        losses[step] = loss.detach()
    ensemble.train(was_training)
    return losses

